//! Request parameters: parsed strictly and bounded before anything is rendered. Every
//! problem is a [`BadRequest`] naming the parameter and what was expected (a 400 answer).

use std::collections::HashMap;

use crate::pass::PassOptions;

/// Largest render side in pixels.
pub const MAX_SIDE: usize = 1024;
/// Largest coordinate of a camera position or target (world units; the scenes are metres).
pub const MAX_COORD: f32 = 1e4;
/// Field of view bounds, degrees.
pub const FOV_RANGE: (f64, f64) = (1.0, 150.0);

/// A request the server refuses (HTTP 400), with the reason.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BadRequest(pub String);

impl std::fmt::Display for BadRequest {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

fn bad<T>(msg: impl Into<String>) -> Result<T, BadRequest> {
    Err(BadRequest(msg.into()))
}

/// Where the camera is.
#[derive(Debug, Clone, PartialEq)]
pub enum CamSpec {
    /// Dataset camera row `c`, exactly (resized to the requested size).
    Dataset(usize),
    /// A camera at `eye` looking at `target`, the image's up toward the head.
    Free {
        eye: [f32; 3],
        target: [f32; 3],
        fov_deg: f64,
    },
}

/// `GET /api/render?...`
#[derive(Debug, Clone, PartialEq)]
pub struct RenderRequest {
    pub pose: usize,
    pub cam: CamSpec,
    pub width: usize,
    pub height: usize,
    pub pass: PassOptions,
    /// Score against the ground truth when this is a dataset image at its own size.
    pub score: bool,
}

/// The query string's `key=value` pairs, percent-decoded. A key given twice, an empty key
/// or a key outside `allowed` is refused.
pub fn pairs<'a>(query: &'a str, allowed: &[&str]) -> Result<HashMap<&'a str, String>, BadRequest> {
    let mut out = HashMap::new();
    for part in query.split('&').filter(|p| !p.is_empty()) {
        let (k, v) = part.split_once('=').unwrap_or((part, ""));
        if !allowed.contains(&k) {
            return bad(format!(
                "unknown parameter {:?} (expected one of {})",
                truncate(k),
                allowed.join(", ")
            ));
        }
        let v = percent_decode(v)
            .ok_or_else(|| BadRequest(format!("parameter {k}: malformed percent-encoding")))?;
        if out.insert(k, v).is_some() {
            return bad(format!("parameter {k} given twice"));
        }
    }
    Ok(out)
}

fn truncate(s: &str) -> String {
    s.chars().take(40).collect()
}

fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'%' => {
                let hex = std::str::from_utf8(b.get(i + 1..i + 3)?).ok()?;
                out.push(u8::from_str_radix(hex, 16).ok()?);
                i += 3;
            }
            b'+' => {
                out.push(b' ');
                i += 1;
            }
            c => {
                out.push(c);
                i += 1;
            }
        }
    }
    String::from_utf8(out).ok()
}

/// A non-negative integer parameter below `bound` (`what` says what the bound is).
pub fn index(
    q: &HashMap<&str, String>,
    key: &str,
    bound: usize,
    what: &str,
) -> Result<Option<usize>, BadRequest> {
    let Some(v) = q.get(key) else {
        return Ok(None);
    };
    match v.trim().parse::<usize>() {
        Ok(i) if i < bound => Ok(Some(i)),
        Ok(i) => bad(format!("{key}={i} is past the {bound} {what}")),
        Err(_) => bad(format!(
            "{key}={:?}: expected an integer in 0..{bound}",
            truncate(v)
        )),
    }
}

fn flag(q: &HashMap<&str, String>, key: &str, default: bool) -> Result<bool, BadRequest> {
    match q.get(key).map(|v| v.as_str()) {
        None => Ok(default),
        Some("1") | Some("true") => Ok(true),
        Some("0") | Some("false") => Ok(false),
        Some(v) => bad(format!("{key}={:?}: expected 0 or 1", truncate(v))),
    }
}

fn side(q: &HashMap<&str, String>, key: &str) -> Result<Option<usize>, BadRequest> {
    let Some(v) = q.get(key) else {
        return Ok(None);
    };
    match v.trim().parse::<usize>() {
        Ok(n) if (1..=MAX_SIDE).contains(&n) => Ok(Some(n)),
        _ => bad(format!(
            "{key}={:?}: expected an image side in 1..={MAX_SIDE} pixels",
            truncate(v)
        )),
    }
}

fn vec3(q: &HashMap<&str, String>, key: &str) -> Result<[f32; 3], BadRequest> {
    let v = q
        .get(key)
        .ok_or_else(|| BadRequest(format!("{key} is missing (x,y,z)")))?;
    let parts: Vec<&str> = v.split(',').collect();
    let nums: Option<Vec<f32>> = parts.iter().map(|p| p.trim().parse::<f32>().ok()).collect();
    match nums {
        Some(n) if n.len() == 3 && n.iter().all(|x| x.is_finite() && x.abs() <= MAX_COORD) => {
            Ok([n[0], n[1], n[2]])
        }
        _ => bad(format!(
            "{key}={:?}: expected three finite numbers x,y,z with |x| <= {MAX_COORD}",
            truncate(v)
        )),
    }
}

/// The parameters of `GET /api/render` for a scene with `poses` poses and `cameras`
/// dataset cameras; `default_size` applies when `w`/`h` are absent.
pub fn render_request(
    query: &str,
    poses: usize,
    cameras: usize,
    default_size: (usize, usize),
) -> Result<RenderRequest, BadRequest> {
    let q = pairs(
        query,
        &[
            "pose",
            "cam",
            "eye",
            "target",
            "fov",
            "w",
            "h",
            "cull_rays",
            "cull_samples",
            "occupancy",
            "early_stop",
            "cull_joints",
            "score",
        ],
    )?;
    let pose = index(&q, "pose", poses, "poses")?.unwrap_or(0);
    let free = ["eye", "target", "fov"].iter().any(|k| q.contains_key(k));
    let cam = match (index(&q, "cam", cameras, "dataset cameras")?, free) {
        (Some(_), true) => return bad("give either cam=C or eye, target and fov, not both"),
        (Some(c), false) => CamSpec::Dataset(c),
        (None, _) => {
            let fov = q
                .get("fov")
                .ok_or_else(|| BadRequest("fov is missing (degrees)".into()))?;
            let fov_deg = match fov.trim().parse::<f64>() {
                Ok(f) if f >= FOV_RANGE.0 && f <= FOV_RANGE.1 => f,
                _ => {
                    return bad(format!(
                        "fov={:?}: expected degrees in [{}, {}]",
                        truncate(fov),
                        FOV_RANGE.0,
                        FOV_RANGE.1
                    ))
                }
            };
            CamSpec::Free {
                eye: vec3(&q, "eye")?,
                target: vec3(&q, "target")?,
                fov_deg,
            }
        }
    };
    let width = side(&q, "w")?.unwrap_or(default_size.0);
    let height = side(&q, "h")?.unwrap_or(default_size.1);
    Ok(RenderRequest {
        pose,
        cam,
        width,
        height,
        pass: PassOptions {
            cull_rays: flag(&q, "cull_rays", true)?,
            cull_samples: flag(&q, "cull_samples", true)?,
            occupancy: flag(&q, "occupancy", false)?,
            early_stop: flag(&q, "early_stop", false)?,
            cull_joints: flag(&q, "cull_joints", true)?,
        },
        score: flag(&q, "score", false)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn req(q: &str) -> Result<RenderRequest, BadRequest> {
        render_request(q, 10, 2, (64, 48))
    }

    #[test]
    fn dataset_and_free_cameras() {
        let r = req("pose=3&cam=1&w=32&h=24&cull_rays=0&score=1").unwrap();
        assert_eq!(r.pose, 3);
        assert_eq!(r.cam, CamSpec::Dataset(1));
        assert_eq!((r.width, r.height), (32, 24));
        assert!(!r.pass.cull_rays && r.pass.cull_samples && !r.pass.occupancy);
        assert!(r.score);
        assert!(req("cam=0&occupancy=1").unwrap().pass.occupancy);
        assert!(!r.pass.early_stop && req("cam=0&early_stop=1").unwrap().pass.early_stop);
        assert!(r.pass.cull_joints && !req("cam=0&cull_joints=0").unwrap().pass.cull_joints);
        // URLSearchParams encodes commas.
        let r = req("pose=0&eye=0%2C-1%2C3&target=0,0.5,0&fov=30").unwrap();
        assert_eq!(
            r.cam,
            CamSpec::Free {
                eye: [0.0, -1.0, 3.0],
                target: [0.0, 0.5, 0.0],
                fov_deg: 30.0
            }
        );
        assert_eq!((r.width, r.height), (64, 48));
        assert!(r.pass.cull_rays && r.pass.cull_samples);
        assert!(!r.score);
    }

    #[test]
    fn refuses_out_of_range_and_malformed_values() {
        for q in [
            "pose=10&cam=0",
            "pose=-1&cam=0",
            "pose=abc&cam=0",
            "pose=99999999999999999999999&cam=0",
            "cam=2",
            "cam=0&w=0",
            "cam=0&w=1025",
            "cam=0&h=1e9",
            "cam=0&cull_rays=maybe",
            "cam=0&cull=1",
            "cam=0&eye=0,0,1",
            "eye=0,0,1&target=0,0,0",
            "eye=0,0,1&target=0,0,0&fov=0",
            "eye=0,0,1&target=0,0,0&fov=nan",
            "eye=nan,0,1&target=0,0,0&fov=30",
            "eye=1e9,0,1&target=0,0,0&fov=30",
            "eye=0,0&target=0,0,0&fov=30",
            "eye=0,0,1,2&target=0,0,0&fov=30",
            "cam=0&cam=1",
            "cam=0&file=/etc/passwd",
            "cam=0&w=%zz",
            "cam=0&w=%ff",
        ] {
            let e = req(q).expect_err(q);
            assert!(!e.0.is_empty(), "{q}");
        }
    }

    #[test]
    fn percent_decoding() {
        assert_eq!(percent_decode("a%2Cb+c").as_deref(), Some("a,b c"));
        assert_eq!(percent_decode("%"), None);
        assert_eq!(percent_decode("%4"), None);
        assert_eq!(percent_decode("%C3%A9").as_deref(), Some("é"));
        assert_eq!(percent_decode("%C3"), None);
    }
}
