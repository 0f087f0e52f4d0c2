//! The pixel members of an `.h5`: checked shapes, then streamed one image at
//! a time into the output archive after the scene members.

use std::{
    fs::File,
    io::{BufWriter, Seek, Write},
    path::Path,
};

use npyz::{DType, TypeStr, WriterBuilder};
use pma_data::{
    dataset::{Compression, Dataset, Profile, Warning, WriteOptions},
    fsio::{AtomicFile, Latch, Writer},
};

use super::{DatasetOptions, DatasetReport, Layout, Progress};
use crate::{
    error::{ConvertError, Result},
    h5::H5File,
};

/// One pixel member to stream: its source key and the channel count written.
#[derive(Clone, Debug)]
pub(super) struct PixelMember {
    pub(super) key: &'static str,
    pub(super) rows: usize,
    pub(super) channels_in: usize,
    pub(super) channels_out: usize,
}

/// The pixel members of an `.h5` and their checked shapes.
#[derive(Clone, Debug, Default)]
pub(super) struct PixelPlan {
    pub(super) members: Vec<PixelMember>,
    /// Mixamo's white plate, written in place of a stored `bkgds`.
    white_plate: bool,
    hw: usize,
}

impl PixelPlan {
    pub(super) fn new(h5: &H5File, keys: &[String], ds: &Dataset, layout: Layout) -> Result<Self> {
        let path = h5.path();
        let n = ds.n_images();
        let hw = ds.height() * ds.width();
        let mut members = Vec::new();
        for (key, channels) in [
            ("imgs", 3usize),
            ("masks", 1),
            ("sampling_masks", 1),
            ("bkgds", 3),
        ] {
            if !keys.iter().any(|k| k == key) || (key == "bkgds" && layout == Layout::Mixamo) {
                continue;
            }
            if ds.img_shape.is_none() {
                return Err(ConvertError::missing(
                    path,
                    "img_shape",
                    format!(" (needed to read `{key}`)"),
                ));
            }
            let info = h5.info(key)?;
            let s = &info.shape;
            let expect = format!("(n, H·W = {hw}, {channels}) uint8");
            if info.kind
                != (crate::h5::H5Kind::Int {
                    size: 1,
                    signed: false,
                })
            {
                return Err(ConvertError::mismatch(
                    path,
                    key,
                    expect,
                    format!("{} of shape {s:?}", info.kind),
                ));
            }
            let c_in = match s.as_slice() {
                [_, p, c] if *p == hw => *c,
                _ => {
                    return Err(ConvertError::mismatch(
                        path,
                        key,
                        expect,
                        format!("shape {s:?}"),
                    ))
                }
            };
            if key != "bkgds" && s[0] != n {
                return Err(ConvertError::mismatch(
                    path,
                    key,
                    format!("{n} rows (img_shape[0])"),
                    format!("{} rows", s[0]),
                ));
            }
            let c_out = if channels == 3 && c_in == 4 { 3 } else { c_in };
            if c_in != channels && !(channels == 3 && c_in == 4) {
                return Err(ConvertError::mismatch(
                    path,
                    key,
                    expect,
                    format!("shape {s:?}"),
                ));
            }
            members.push(PixelMember {
                key,
                rows: s[0],
                channels_in: c_in,
                channels_out: c_out,
            });
        }
        Ok(Self {
            members,
            white_plate: layout == Layout::Mixamo,
            hw,
        })
    }

    pub(super) fn get(&self, key: &str) -> Option<&PixelMember> {
        self.members.iter().find(|m| m.key == key)
    }

    pub(super) fn n_backgrounds(&self) -> Option<usize> {
        if self.white_plate {
            Some(1)
        } else {
            self.get("bkgds").map(|m| m.rows)
        }
    }
}

#[allow(clippy::too_many_arguments)]
pub(super) fn write_h5_output(
    h5: &H5File,
    ds: &Dataset,
    plan: &PixelPlan,
    streamed: &[&PixelMember],
    output: &Path,
    opts: &DatasetOptions,
    rep: &mut DatasetReport,
    progress: Progress,
) -> Result<()> {
    write_archive(ds, output, opts.compression, |zip| {
        let total: u64 =
            streamed.iter().map(|m| m.rows as u64).sum::<u64>() + plan.white_plate as u64;
        let mut done = 0u64;
        progress(done, total);
        for m in streamed {
            let shape = [m.rows, plan.hw, m.channels_out];
            start_member(zip, output, m.key, &shape, opts.compression)?;
            for row in 0..m.rows {
                pma_data::interrupt::check()?;
                let raw = h5.read_u8_rows(m.key, row, row + 1)?;
                let px = prepare_row(raw, m, row, opts, h5.path(), rep)?;
                zip.write_all(&px)
                    .map_err(|e| ConvertError::write(output, e))?;
                done += 1;
                progress(done, total);
            }
        }
        if plan.white_plate && opts.profile >= Profile::Render {
            start_member(zip, output, "bkgds", &[1, plan.hw, 3], opts.compression)?;
            // In pieces: a plate is as large as one image, whatever that is.
            let piece = vec![255u8; (plan.hw * 3).min(1 << 20)];
            let mut left = plan.hw * 3;
            while left > 0 {
                let k = left.min(piece.len());
                zip.write_all(&piece[..k])
                    .map_err(|e| ConvertError::write(output, e))?;
                left -= k;
            }
            done += 1;
            progress(done, total);
        }
        Ok(())
    })
}

/// The zip a converter streams pixels into (see [`write_archive`]).
pub(crate) type ArchiveZip<'a> = zip::ZipWriter<Latch<BufWriter<Writer<&'a File>>>>;

/// A converted archive, written atomically: the scene members the data layer writes for
/// `ds`, copied verbatim, then the pixel members `pixels` streams into the zip. A failed
/// write (a full disk) is [`ConvertError::Write`], and nothing is left behind.
pub(crate) fn write_archive(
    ds: &Dataset,
    output: &Path,
    compression: Compression,
    pixels: impl FnOnce(&mut ArchiveZip<'_>) -> Result<()>,
) -> Result<()> {
    // The scene members go through a scratch file; a failure there is writing `output`.
    let scene =
        pma_data::fsio::scratch_beside(output).map_err(|e| ConvertError::write(output, e))?;
    ds.write(scene.path(), &WriteOptions { compression })
        .map_err(|e| match e {
            pma_data::DataError::File(pma_data::FileError::Write { source, .. }) => {
                ConvertError::write(output, source)
            }
            e => e.into(),
        })?;
    let scene_zip = zip::ZipArchive::new(
        File::open(scene.path()).map_err(|e| ConvertError::write(scene.path(), e))?,
    )
    .map_err(|cause| ConvertError::Zip {
        path: scene.path().to_path_buf(),
        cause,
    })?;
    let out = AtomicFile::create(output).map_err(|e| ConvertError::write(output, e))?;
    let latch = Latch::new(BufWriter::new(out.writer()));
    let watch = latch.watch();
    let mut zip = zip::ZipWriter::new(latch);
    // A failure of the sink is a write failure; anything else the zip says is its own.
    let zerr = |cause| match watch.failure() {
        Some(io) => ConvertError::write(output, io),
        None => match cause {
            zip::result::ZipError::Io(io) => ConvertError::write(output, io),
            cause => ConvertError::Zip {
                path: output.to_path_buf(),
                cause,
            },
        },
    };
    zip.merge_archive(scene_zip).map_err(zerr)?;
    if let Err(e) = pixels(&mut zip) {
        // The pixel writers report the sink's error as they met it; the first one counts.
        return Err(match watch.failure() {
            Some(io) => ConvertError::write(output, io),
            None => e,
        });
    }
    let latch = zip.finish().map_err(zerr)?;
    if let Some(e) = watch.failure() {
        return Err(ConvertError::write(output, e));
    }
    let mut buf = latch.into_inner();
    buf.flush().map_err(|e| ConvertError::write(output, e))?;
    drop(buf);
    out.commit().map_err(|e| ConvertError::write(output, e))
}

/// Checks one row of pixels (mask values, empty sampling masks) and converts
/// it to the stored form.
fn prepare_row(
    raw: Vec<u8>,
    m: &PixelMember,
    row: usize,
    opts: &DatasetOptions,
    input: &Path,
    rep: &mut DatasetReport,
) -> Result<Vec<u8>> {
    let mut px = if m.channels_in != m.channels_out {
        raw.chunks_exact(m.channels_in)
            .flat_map(|c| c[..m.channels_out].iter().copied())
            .collect()
    } else {
        raw
    };
    match m.key {
        "masks" => {
            if let Some(pos) = px.iter().position(|&v| v > 1) {
                if !opts.binarize_masks {
                    return Err(ConvertError::invalid(
                        input,
                        "masks",
                        format!(
                            "image {row}, pixel {pos}: value {} is not 0 or 1 (pass --binarize-masks for 0/255 masks)",
                            px[pos]
                        ),
                    ));
                }
                for v in &mut px {
                    *v = (*v >= 2) as u8;
                }
            }
        }
        "sampling_masks" if px.iter().all(|&v| v == 0) => {
            rep.warnings.push(Warning {
                key: "sampling_masks".into(),
                message: format!(
                    "image {row} allows no pixel; the reference falls back to sampling every pixel"
                ),
            });
        }
        _ => {}
    }
    Ok(px)
}

/// Starts `<key>.npy` in the archive and writes its NPY header; the payload
/// is appended by the caller. Options match the data layer's writer (fixed
/// timestamp and permissions) so outputs are byte-deterministic.
pub(crate) fn start_member<W: Write + Seek>(
    zip: &mut zip::ZipWriter<W>,
    output: &Path,
    key: &str,
    shape: &[usize],
    compression: Compression,
) -> Result<()> {
    let payload: u64 = shape.iter().map(|&d| d as u64).product();
    let method = match compression {
        Compression::Stored => zip::CompressionMethod::Stored,
        Compression::Deflated => zip::CompressionMethod::Deflated,
    };
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(method)
        .last_modified_time(zip::DateTime::default())
        .unix_permissions(0o644)
        .large_file(payload + 4096 >= u32::MAX as u64);
    zip.start_file(format!("{key}.npy"), options)
        .map_err(|source| match source {
            zip::result::ZipError::Io(e) => ConvertError::write(output, e),
            cause => ConvertError::Zip {
                path: output.to_path_buf(),
                cause,
            },
        })?;
    let ts: TypeStr = "|u1".parse().expect("static dtype descriptor");
    let shape64: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    npyz::WriteOptions::new_header_only()
        .dtype(DType::Plain(ts))
        .shape(&shape64)
        .writer(&mut *zip)
        .write_header_only()
        .map_err(|e| ConvertError::write(output, e))?;
    Ok(())
}
