//! [`Dataset`] → npz, atomically (through [`crate::fsio`]) and
//! byte-deterministically (fixed member order, timestamps and permissions).

use std::io::{BufWriter, Write};
use std::path::Path;

use super::npz::{MemberData, NpzWriter};
use super::Dataset;
use crate::error::{DataError, Result};
use crate::fsio::{parent_dir, AtomicFile};

/// How members are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Compression {
    /// `np.savez`: fast, and allows memory-mapped access to pixels.
    #[default]
    Stored,
    /// `np.savez_compressed`.
    Deflated,
}

/// Options for [`Dataset::write`].
#[derive(Debug, Clone, Copy, Default)]
pub struct WriteOptions {
    pub compression: Compression,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Members {
    All,
    Scene,
    Frames,
}

pub(crate) fn write_npz(
    ds: &Dataset,
    path: &Path,
    opts: &WriteOptions,
    which: Members,
) -> Result<()> {
    let tmp = AtomicFile::create(path).map_err(|e| DataError::io(parent_dir(path), e))?;
    {
        let buf = BufWriter::new(tmp.file());
        let mut w = NpzWriter::new(
            buf,
            opts.compression == Compression::Deflated,
            path.display().to_string(),
        );
        if which != Members::Frames {
            scene_members(ds, &mut w)?;
        }
        if which != Members::Scene {
            frame_members(ds, &mut w)?;
        }
        let mut buf = w.finish()?;
        buf.flush().map_err(|e| DataError::io(path, e))?;
    }
    tmp.commit().map_err(|e| DataError::io(path, e))
}

fn std_slice<'a, T, D: ndarray::Dimension>(
    a: &'a ndarray::Array<T, D>,
    key: &str,
) -> Result<&'a [T]> {
    a.as_slice()
        .ok_or_else(|| DataError::arg(key, "a C-contiguous array", "a non-contiguous view"))
}

fn scene_members<W: Write + std::io::Seek>(ds: &Dataset, w: &mut NpzWriter<W>) -> Result<()> {
    w.add("schema_version", &[], MemberData::I32(&[ds.schema_version]))?;
    if let Some(r) = &ds.rest_pose {
        let flat: Vec<f32> = r.iter().flatten().copied().collect();
        w.add("rest_pose", &[24, 3], MemberData::F32(&flat))?;
    }
    w.add(
        "bones",
        ds.bones.shape(),
        MemberData::F32(std_slice(&ds.bones, "bones")?),
    )?;
    if let Some(a) = &ds.kp3d {
        w.add("kp3d", a.shape(), MemberData::F32(std_slice(a, "kp3d")?))?;
    }
    if let Some(a) = &ds.root_locs {
        w.add(
            "root_locs",
            a.shape(),
            MemberData::F32(std_slice(a, "root_locs")?),
        )?;
    }
    if let Some(a) = &ds.skts {
        w.add("skts", a.shape(), MemberData::F32(std_slice(a, "skts")?))?;
    }
    if let Some(a) = &ds.cyls {
        w.add("cyls", a.shape(), MemberData::F32(std_slice(a, "cyls")?))?;
    }
    if let Some(a) = &ds.betas {
        w.add("betas", a.shape(), MemberData::F32(std_slice(a, "betas")?))?;
    }
    if let Some(a) = &ds.gt_kp3d {
        w.add(
            "gt_kp3d",
            a.shape(),
            MemberData::F32(std_slice(a, "gt_kp3d")?),
        )?;
    }
    if let Some(a) = &ds.frame_ids {
        w.add(
            "frame_ids",
            a.shape(),
            MemberData::I64(std_slice(a, "frame_ids")?),
        )?;
    }
    w.add("head_dir", &[3], MemberData::F32(&ds.head_dir))?;
    w.add("pose_scale", &[], MemberData::F32(&[ds.pose_scale]))?;
    if let Some(e) = ds.ext_scale {
        w.add("ext_scale", &[], MemberData::F64(&[e]))?;
    }
    if let Some(a) = &ds.c2ws {
        w.add("c2ws", a.shape(), MemberData::F32(std_slice(a, "c2ws")?))?;
    }
    if let Some(a) = &ds.focals {
        w.add(
            "focals",
            a.shape(),
            MemberData::F32(std_slice(a, "focals")?),
        )?;
    }
    if let Some(a) = &ds.centers {
        w.add(
            "centers",
            a.shape(),
            MemberData::F32(std_slice(a, "centers")?),
        )?;
    }
    if let Some(s) = ds.img_shape {
        let v = s.map(|x| x as i64);
        w.add("img_shape", &[4], MemberData::I64(&v))?;
    }
    for (key, a) in [
        ("kp_idxs", &ds.kp_idxs),
        ("img_pose_indices", &ds.img_pose_indices),
        ("bkgd_idxs", &ds.bkgd_idxs),
    ] {
        if let Some(a) = a {
            w.add(key, a.shape(), MemberData::I64(std_slice(a, key)?))?;
        }
    }
    if let Some(a) = &ds.eval_tag {
        w.add(
            "eval_tag",
            a.shape(),
            MemberData::I8(std_slice(a, "eval_tag")?),
        )?;
    }
    Ok(())
}

fn frame_members<W: Write + std::io::Seek>(ds: &Dataset, w: &mut NpzWriter<W>) -> Result<()> {
    for (key, a) in [
        ("imgs", &ds.imgs),
        ("masks", &ds.masks),
        ("sampling_masks", &ds.sampling_masks),
        ("bkgds", &ds.bkgds),
    ] {
        if let Some(a) = a {
            w.add(key, a.shape(), MemberData::U8(std_slice(a, key)?))?;
        }
    }
    Ok(())
}
