//! [`Dataset`] → npz, atomically (through [`crate::fsio`]) and
//! byte-deterministically (fixed member order, timestamps and permissions).

use std::io::{BufWriter, Seek, Write};
use std::path::Path;

use super::npz::{MemberData, NpzWriter};
use super::Dataset;
use crate::error::{DataError, Result};
use crate::fsio::AtomicFile;

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
    let tmp = AtomicFile::create(path).map_err(|e| DataError::write(path, e))?;
    {
        let buf = BufWriter::new(tmp.writer());
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
        buf.flush().map_err(|e| DataError::write(path, e))?;
    }
    tmp.commit().map_err(|e| DataError::write(path, e))
}

fn std_slice<'a, T, D: ndarray::Dimension>(
    a: &'a ndarray::Array<T, D>,
    key: &str,
) -> Result<&'a [T]> {
    a.as_slice()
        .ok_or_else(|| DataError::arg(key, "a C-contiguous array", "a non-contiguous view"))
}

/// Adds array `a` as member `key`; `data` picks the element type.
fn add<'a, W: Write + Seek, T, D: ndarray::Dimension>(
    w: &mut NpzWriter<W>,
    key: &str,
    a: &'a ndarray::Array<T, D>,
    data: fn(&'a [T]) -> MemberData<'a>,
) -> Result<()> {
    w.add(key, a.shape(), data(std_slice(a, key)?))
}

/// [`add`] for an optional array; an absent one is not written.
fn add_opt<'a, W: Write + Seek, T, D: ndarray::Dimension>(
    w: &mut NpzWriter<W>,
    key: &str,
    a: &'a Option<ndarray::Array<T, D>>,
    data: fn(&'a [T]) -> MemberData<'a>,
) -> Result<()> {
    match a {
        Some(a) => add(w, key, a, data),
        None => Ok(()),
    }
}

fn scene_members<W: Write + Seek>(ds: &Dataset, w: &mut NpzWriter<W>) -> Result<()> {
    use MemberData::{F32, I64, I8};
    w.add("schema_version", &[], MemberData::I32(&[ds.schema_version]))?;
    if let Some(r) = &ds.rest_pose {
        let flat: Vec<f32> = r.iter().flatten().copied().collect();
        w.add("rest_pose", &[24, 3], F32(&flat))?;
    }
    add(w, "bones", &ds.bones, F32)?;
    add_opt(w, "kp3d", &ds.kp3d, F32)?;
    add_opt(w, "root_locs", &ds.root_locs, F32)?;
    add_opt(w, "skts", &ds.skts, F32)?;
    add_opt(w, "cyls", &ds.cyls, F32)?;
    add_opt(w, "betas", &ds.betas, F32)?;
    add_opt(w, "gt_kp3d", &ds.gt_kp3d, F32)?;
    add_opt(w, "frame_ids", &ds.frame_ids, I64)?;
    w.add("head_dir", &[3], F32(&ds.head_dir))?;
    w.add("pose_scale", &[], F32(&[ds.pose_scale]))?;
    if let Some(e) = ds.ext_scale {
        w.add("ext_scale", &[], MemberData::F64(&[e]))?;
    }
    add_opt(w, "c2ws", &ds.c2ws, F32)?;
    add_opt(w, "focals", &ds.focals, F32)?;
    add_opt(w, "centers", &ds.centers, F32)?;
    if let Some(s) = ds.img_shape {
        let v = s.map(|x| x as i64);
        w.add("img_shape", &[4], I64(&v))?;
    }
    add_opt(w, "kp_idxs", &ds.kp_idxs, I64)?;
    add_opt(w, "img_pose_indices", &ds.img_pose_indices, I64)?;
    add_opt(w, "bkgd_idxs", &ds.bkgd_idxs, I64)?;
    add_opt(w, "eval_tag", &ds.eval_tag, I8)
}

fn frame_members<W: Write + Seek>(ds: &Dataset, w: &mut NpzWriter<W>) -> Result<()> {
    add_opt(w, "imgs", &ds.imgs, MemberData::U8)?;
    add_opt(w, "masks", &ds.masks, MemberData::U8)?;
    add_opt(w, "sampling_masks", &ds.sampling_masks, MemberData::U8)?;
    add_opt(w, "bkgds", &ds.bkgds, MemberData::U8)
}
