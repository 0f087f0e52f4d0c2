//! Biovision Hierarchy (BVH) motion files: parser and forward kinematics.
//!
//! A BVH file has a `HIERARCHY` section (a joint tree with per-joint offsets
//! and channel lists) and a `MOTION` section (one line of channel values per
//! frame). Rotations are Euler angles in degrees, composed in the order the
//! channels are listed: `CHANNELS 3 Zrotation Xrotation Yrotation` means
//! `R = Rz(a)·Rx(b)·Ry(c)`. Channel orders may differ per joint (the CMU
//! "cmuconvert" files use ZYX for the legs and spine and ZXY for the arms).
//!
//! Units are whatever the file uses; [`Bvh::pose`] reports positions in file
//! units and the caller scales them.

use std::path::Path;

use glam::{DMat3, DVec3};

use super::MotionError;

/// One animation channel of a joint.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Channel {
    Xposition,
    Yposition,
    Zposition,
    Xrotation,
    Yrotation,
    Zrotation,
}

impl Channel {
    fn parse(token: &str) -> Option<Self> {
        Some(match token {
            "Xposition" => Channel::Xposition,
            "Yposition" => Channel::Yposition,
            "Zposition" => Channel::Zposition,
            "Xrotation" => Channel::Xrotation,
            "Yrotation" => Channel::Yrotation,
            "Zrotation" => Channel::Zrotation,
            _ => return None,
        })
    }
}

/// A joint of the hierarchy. Joints are stored in file order, so a parent
/// always comes before its children.
#[derive(Clone, Debug)]
pub struct BvhJoint {
    pub name: String,
    pub parent: Option<usize>,
    /// Rest offset from the parent joint, in the parent's frame (file units).
    pub offset: [f64; 3],
    pub channels: Vec<Channel>,
    /// Index of this joint's first channel within a frame's values.
    pub first_channel: usize,
    /// `End Site` offset, if the joint ends a chain.
    pub end_site: Option<[f64; 3]>,
}

/// A parsed BVH file.
#[derive(Clone, Debug)]
pub struct Bvh {
    pub joints: Vec<BvhJoint>,
    /// Seconds per frame.
    pub frame_time: f64,
    /// Channel values, `[n_frames × n_channels]` row-major.
    values: Vec<f64>,
    n_channels: usize,
}

/// World-space state of every joint for one frame (file units).
#[derive(Clone, Debug)]
pub struct BvhPose {
    /// Accumulated rotation of each joint's frame, parent-to-world included.
    pub rotation: Vec<DMat3>,
    /// Position of each joint.
    pub position: Vec<DVec3>,
}

impl BvhPose {
    /// World position of joint `j`'s end site, if it has one.
    pub fn end_site(&self, bvh: &Bvh, j: usize) -> Option<DVec3> {
        let e = bvh.joints[j].end_site?;
        Some(self.position[j] + self.rotation[j] * DVec3::from(e))
    }
}

/// Whitespace tokens with the 1-based line each came from.
struct Tokens<'a> {
    items: Vec<(usize, &'a str)>,
    next: usize,
    file: &'a str,
}

impl<'a> Tokens<'a> {
    fn new(text: &'a str, file: &'a str) -> Self {
        let items = text
            .lines()
            .enumerate()
            .flat_map(|(i, line)| line.split_whitespace().map(move |t| (i + 1, t)))
            .collect();
        Tokens {
            items,
            next: 0,
            file,
        }
    }

    fn line(&self) -> usize {
        self.items
            .get(self.next.min(self.items.len().saturating_sub(1)))
            .map_or(0, |&(l, _)| l)
    }

    fn err_at(&self, line: usize, msg: impl Into<String>) -> MotionError {
        MotionError::Bvh {
            file: self.file.to_string(),
            line,
            msg: msg.into(),
        }
    }

    fn err(&self, msg: impl Into<String>) -> MotionError {
        MotionError::Bvh {
            file: self.file.to_string(),
            line: self.line(),
            msg: msg.into(),
        }
    }

    fn next(&mut self, what: &str) -> Result<&'a str, MotionError> {
        match self.items.get(self.next) {
            Some(&(_, t)) => {
                self.next += 1;
                Ok(t)
            }
            None => Err(self.err(format!("unexpected end of file, expected {what}"))),
        }
    }

    fn peek(&self) -> Option<&'a str> {
        self.items.get(self.next).map(|&(_, t)| t)
    }

    fn expect(&mut self, word: &str) -> Result<(), MotionError> {
        let t = self.next(&format!("`{word}`"))?;
        if t == word {
            Ok(())
        } else {
            self.next -= 1;
            Err(self.err(format!("expected `{word}`, found `{t}`")))
        }
    }

    fn number(&mut self, what: &str) -> Result<f64, MotionError> {
        let t = self.next(what)?;
        match t.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => {
                self.next -= 1;
                Err(self.err(format!("expected {what} (a finite number), found `{t}`")))
            }
        }
    }

    fn vec3(&mut self, what: &str) -> Result<[f64; 3], MotionError> {
        Ok([self.number(what)?, self.number(what)?, self.number(what)?])
    }
}

impl Bvh {
    /// Reads and parses a BVH file.
    pub fn read(path: &Path) -> Result<Self, MotionError> {
        // A BVH of 64 MiB holds hours of motion; larger is not a motion file.
        let text = crate::fsio::read_input_to_string(path, 64 << 20).map_err(|source| {
            MotionError::Io {
                path: path.to_path_buf(),
                source,
            }
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses BVH text; `file` names the source in error messages.
    pub fn parse(text: &str, file: &str) -> Result<Self, MotionError> {
        let mut tok = Tokens::new(text, file);
        tok.expect("HIERARCHY")?;
        tok.expect("ROOT")?;
        let mut joints = Vec::new();
        let mut n_channels = 0;
        parse_joint(&mut tok, None, &mut joints, &mut n_channels)?;
        if tok.peek() != Some("MOTION") {
            return Err(tok.err(format!(
                "expected `MOTION` after the root joint's closing brace, found `{}`",
                tok.peek().unwrap_or("end of file")
            )));
        }
        tok.expect("MOTION")?;
        tok.expect("Frames:")?;
        let frames_line = tok.line();
        let n_frames = tok.number("the frame count")?;
        if n_frames < 1.0 || n_frames.fract() != 0.0 {
            // Report the `Frames:` line itself, not the token after it.
            return Err(tok.err_at(
                frames_line,
                format!("expected a positive integer frame count, found {n_frames}"),
            ));
        }
        let n_frames = n_frames as usize;
        tok.expect("Frame")?;
        tok.expect("Time:")?;
        let frame_time = tok.number("the frame time")?;
        if frame_time <= 0.0 {
            return Err(tok.err(format!(
                "expected a positive frame time, found {frame_time}"
            )));
        }
        // The header's count only sizes the buffer up to what the file holds.
        let remaining = tok.items.len().saturating_sub(tok.next);
        let mut values = Vec::with_capacity(n_frames.saturating_mul(n_channels).min(remaining));
        for f in 0..n_frames {
            for c in 0..n_channels {
                if tok.peek().is_none() {
                    return Err(tok.err(format!(
                        "file ends inside frame {f} (channel {c} of {n_channels}); \
                         the header announces {n_frames} frames"
                    )));
                }
                values.push(tok.number("a channel value")?);
            }
        }
        if let Some(extra) = tok.peek() {
            return Err(tok.err(format!(
                "found `{extra}` after the {n_frames} announced frames of {n_channels} values"
            )));
        }
        Ok(Bvh {
            joints,
            frame_time,
            values,
            n_channels,
        })
    }

    pub fn n_frames(&self) -> usize {
        self.values.len() / self.n_channels.max(1)
    }

    pub fn n_channels(&self) -> usize {
        self.n_channels
    }

    /// Frames per second (`1 / frame_time`).
    pub fn fps(&self) -> f64 {
        1.0 / self.frame_time
    }

    /// Index of the joint called `name`.
    pub fn joint(&self, name: &str) -> Option<usize> {
        self.joints.iter().position(|j| j.name == name)
    }

    /// The channel values of frame `f`: `[n_channels]`.
    pub fn frame(&self, f: usize) -> &[f64] {
        &self.values[f * self.n_channels..(f + 1) * self.n_channels]
    }

    /// World-space joint frames for frame `f` (panics if `f >= n_frames`).
    pub fn pose(&self, f: usize) -> BvhPose {
        self.pose_from_values(self.frame(f))
    }

    /// World-space joint frames with every channel at zero: the skeleton as
    /// the hierarchy's offsets define it.
    pub fn rest(&self) -> BvhPose {
        self.pose_from_values(&vec![0.0; self.n_channels])
    }

    fn pose_from_values(&self, values: &[f64]) -> BvhPose {
        let n = self.joints.len();
        let mut rotation = Vec::with_capacity(n);
        let mut position = Vec::with_capacity(n);
        for joint in &self.joints {
            let mut local_rot = DMat3::IDENTITY;
            let mut local_pos = DVec3::from(joint.offset);
            for (k, ch) in joint.channels.iter().enumerate() {
                let v = values[joint.first_channel + k];
                match ch {
                    Channel::Xposition => local_pos.x += v,
                    Channel::Yposition => local_pos.y += v,
                    Channel::Zposition => local_pos.z += v,
                    Channel::Xrotation => {
                        local_rot *= DMat3::from_rotation_x(v.to_radians());
                    }
                    Channel::Yrotation => {
                        local_rot *= DMat3::from_rotation_y(v.to_radians());
                    }
                    Channel::Zrotation => {
                        local_rot *= DMat3::from_rotation_z(v.to_radians());
                    }
                }
            }
            let (rot, pos) = match joint.parent {
                None => (local_rot, local_pos),
                Some(p) => (
                    rotation[p] * local_rot,
                    position[p] + rotation[p] * local_pos,
                ),
            };
            rotation.push(rot);
            position.push(pos);
        }
        BvhPose { rotation, position }
    }
}

/// Most joints a hierarchy may declare (CMU skeletons have 31).
const MAX_JOINTS: usize = 1024;

/// Parses `name { OFFSET … CHANNELS … children }` after `ROOT`/`JOINT`.
fn parse_joint(
    tok: &mut Tokens<'_>,
    parent: Option<usize>,
    joints: &mut Vec<BvhJoint>,
    n_channels: &mut usize,
) -> Result<(), MotionError> {
    // Skeletons have tens of joints; a bound keeps hostile nesting off the stack.
    if joints.len() >= MAX_JOINTS {
        return Err(tok.err(format!("more than {MAX_JOINTS} joints")));
    }
    let name = tok.next("a joint name")?.to_string();
    if name == "{" {
        tok.next -= 1;
        return Err(tok.err("joint has no name"));
    }
    if joints.iter().any(|j| j.name == name) {
        return Err(tok.err(format!("joint name `{name}` appears twice")));
    }
    tok.expect("{")?;
    tok.expect("OFFSET")?;
    let offset = tok.vec3("an OFFSET component")?;
    tok.expect("CHANNELS")?;
    let count = tok.number("the channel count")?;
    if !(0.0..=6.0).contains(&count) || count.fract() != 0.0 {
        return Err(tok.err(format!(
            "joint `{name}`: expected a channel count in 0..=6, found {count}"
        )));
    }
    let mut channels = Vec::with_capacity(count as usize);
    for _ in 0..count as usize {
        let t = tok.next("a channel name")?;
        let ch = Channel::parse(t).ok_or_else(|| {
            tok.err(format!(
                "joint `{name}`: unknown channel `{t}`, expected X/Y/Z followed by position/rotation"
            ))
        })?;
        if channels.contains(&ch) {
            return Err(tok.err(format!("joint `{name}`: channel `{t}` is listed twice")));
        }
        channels.push(ch);
    }
    let index = joints.len();
    joints.push(BvhJoint {
        name: name.clone(),
        parent,
        offset,
        first_channel: *n_channels,
        channels,
        end_site: None,
    });
    *n_channels += count as usize;
    loop {
        match tok.next("`JOINT`, `End Site` or `}`")? {
            "JOINT" => parse_joint(tok, Some(index), joints, n_channels)?,
            "End" => {
                tok.expect("Site")?;
                tok.expect("{")?;
                tok.expect("OFFSET")?;
                let e = tok.vec3("an End Site OFFSET component")?;
                tok.expect("}")?;
                if joints[index].end_site.replace(e).is_some() {
                    return Err(tok.err(format!("joint `{name}` has two End Sites")));
                }
            }
            "}" => return Ok(()),
            other => {
                tok.next -= 1;
                return Err(tok.err(format!(
                    "inside joint `{name}`: expected `JOINT`, `End Site` or `}}`, found `{other}`"
                )));
            }
        }
    }
}
