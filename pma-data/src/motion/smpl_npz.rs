//! SMPL-parameter npz motion (AIST++ / AMASS style): `poses` `(T,72)` or
//! `(T,24,3)` axis-angle with joint 0 the global orientation, and `trans`
//! `(T,3)` root translation in metres. An optional `mocap_framerate` or
//! `fps` scalar gives the frame rate.
//!
//! SMPL's `trans` is added to the posed pelvis, whose rest position is the
//! subject's own `J0`; with a root-centred rest pose (`rest_pose[0] = 0`,
//! what pma uses) `trans` is the root location up to that constant offset.

use std::io::{Cursor, Read, Seek};
use std::path::Path;

use super::{ambiguous_up, detect_up, Motion, MotionError};
use crate::skeleton::N_JOINTS;

/// Reads an SMPL-parameter npz. `fallback_fps` is used when the file stores
/// no frame rate (AIST++ annotations are 60 fps). The up axis is detected
/// from the root orientations ([`super::detect_up`]).
pub fn read_smpl_npz(path: &Path, fallback_fps: f64) -> Result<Motion, MotionError> {
    let file = crate::fsio::open_input(path).map_err(|source| MotionError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    read_from(
        std::io::BufReader::new(file),
        &path.display().to_string(),
        fallback_fps,
    )
}

/// Like [`read_smpl_npz`] for an npz held in memory; `file` names it in errors.
pub fn parse_smpl_npz(bytes: &[u8], file: &str, fallback_fps: f64) -> Result<Motion, MotionError> {
    read_from(Cursor::new(bytes), file, fallback_fps)
}

fn read_from<R: Read + Seek>(
    reader: R,
    file: &str,
    fallback_fps: f64,
) -> Result<Motion, MotionError> {
    let npz_err = |key: &str, msg: String| MotionError::Npz {
        file: file.to_string(),
        key: key.to_string(),
        msg,
    };
    // npyz multiplies header shapes unchecked; check each member's claim first.
    let mut zip = zip::ZipArchive::new(reader).map_err(|e| npz_err("<archive>", e.to_string()))?;
    for i in 0..zip.len() {
        let m = zip
            .by_index(i)
            .map_err(|e| npz_err("<archive>", e.to_string()))?;
        let key = m
            .name()
            .map_err(|e| npz_err("<archive>", e.to_string()))?
            .trim_end_matches(".npy")
            .to_string();
        let declared = m.size();
        crate::dataset::npz::check_npy_claim(m, declared).map_err(|msg| npz_err(&key, msg))?;
    }
    let mut reader = zip.into_inner();
    reader
        .rewind()
        .map_err(|e| npz_err("<archive>", e.to_string()))?;
    let mut npz =
        npyz::npz::NpzArchive::new(reader).map_err(|e| npz_err("<archive>", e.to_string()))?;

    let (poses, pshape) = read_f64(&mut npz, file, "poses")?
        .ok_or_else(|| npz_err("poses", "missing (expected (T,72) axis-angle)".into()))?;
    let t = match pshape.as_slice() {
        [t, 72] => *t,
        [t, 24, 3] => *t,
        _ => {
            return Err(MotionError::Shape {
                file: file.into(),
                key: "poses".into(),
                expected: "(T,72) or (T,24,3)".into(),
                found: pshape,
            })
        }
    } as usize;
    if t == 0 {
        return Err(MotionError::Shape {
            file: file.into(),
            key: "poses".into(),
            expected: "at least one frame".into(),
            found: pshape,
        });
    }
    let (trans, tshape) = read_f64(&mut npz, file, "trans")?
        .ok_or_else(|| npz_err("trans", "missing (expected (T,3) root translation)".into()))?;
    if tshape != [t as u64, 3] {
        return Err(MotionError::Shape {
            file: file.into(),
            key: "trans".into(),
            expected: format!("({t},3) to match `poses`"),
            found: tshape,
        });
    }
    let mut fps = fallback_fps;
    for key in ["mocap_framerate", "fps"] {
        if let Some((v, shape)) = read_f64(&mut npz, file, key)? {
            if v.len() != 1 {
                return Err(MotionError::Shape {
                    file: file.into(),
                    key: key.into(),
                    expected: "a scalar".into(),
                    found: shape,
                });
            }
            fps = v[0];
            break;
        }
    }

    let mut bones = Vec::with_capacity(t);
    let mut root = Vec::with_capacity(t);
    for f in 0..t {
        let p = &poses[f * 72..(f + 1) * 72];
        if !p.iter().all(|v| v.is_finite()) {
            return Err(MotionError::NonFinite {
                file: file.into(),
                key: "poses".into(),
                frame: f,
            });
        }
        let r = &trans[f * 3..(f + 1) * 3];
        if !r.iter().all(|v| v.is_finite()) {
            return Err(MotionError::NonFinite {
                file: file.into(),
                key: "trans".into(),
                frame: f,
            });
        }
        bones.push(std::array::from_fn::<_, N_JOINTS, _>(|j| {
            std::array::from_fn(|c| p[3 * j + c] as f32)
        }));
        root.push(std::array::from_fn(|c| r[c] as f32));
    }
    let up = detect_up(&bones).ok_or_else(|| ambiguous_up(file, &bones))?;
    let motion = Motion {
        fps,
        bones,
        root,
        up,
    };
    motion.validate()?;
    Ok(motion)
}

/// Reads member `key` as f64 (from f32 or f64 on disk). `None` if absent.
fn read_f64<R: Read + Seek>(
    npz: &mut npyz::npz::NpzArchive<R>,
    file: &str,
    key: &str,
) -> Result<Option<(Vec<f64>, Vec<u64>)>, MotionError> {
    let err = |msg: String| MotionError::Npz {
        file: file.to_string(),
        key: key.to_string(),
        msg,
    };
    let Some(npy) = npz.by_name(key).map_err(|e| err(e.to_string()))? else {
        return Ok(None);
    };
    let shape = npy.shape().to_vec();
    if npy.order() != npyz::Order::C {
        return Err(err("Fortran-ordered array; expected C order".into()));
    }
    let dtype = match npy.dtype() {
        npyz::DType::Plain(ts) => ts.to_string(),
        other => other.descr(),
    };
    let data = match dtype.as_str() {
        "<f4" => npy
            .into_vec::<f32>()
            .map(|v| v.into_iter().map(f64::from).collect()),
        "<f8" => npy.into_vec::<f64>(),
        other => return Err(err(format!("dtype {other}, expected <f4 or <f8"))),
    }
    .map_err(|e| err(e.to_string()))?;
    Ok(Some((data, shape)))
}
