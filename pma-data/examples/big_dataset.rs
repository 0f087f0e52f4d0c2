//! Writes a large pma-npz training file for memory measurements (spec: a 2,000-frame
//! 1000×1000 dataset must be usable on a 24 GiB machine): two synthetic views of one pose at
//! RES×RES, tiled to N images, members stored (not deflated).
//!
//! ```text
//! cargo run --release -p pma-data --example big_dataset -- N OUT.npz [RES]
//! /usr/bin/time -v target/release/pma inspect OUT.npz     # peak RSS
//! ```

use std::time::Instant;

use ndarray::{s, Array1, Array3};
use pma_data::dataset::{Compression, WriteOptions};
use pma_data::synth::{plan, render_split, SynthConfig};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        return Err("usage: big_dataset N OUT.npz [RES]".into());
    }
    let n: usize = args[1].parse()?;
    let out = &args[2];
    let res: usize = args.get(3).map_or(Ok(1000), |r| r.parse())?;
    let t = Instant::now();
    let cfg = SynthConfig::small(res, 2, 1);
    let p = plan(&cfg)?;
    let mut ds = render_split(&p, &p.splits[0], &mut || {})?;
    println!(
        "rendered 2 views at {res}x{res} in {:.1} s",
        t.elapsed().as_secs_f64()
    );
    let hw = res * res;
    let views = ds.n_images();
    let (src_i, src_m, src_s) = (
        ds.imgs.take().ok_or("no imgs")?,
        ds.masks.take().ok_or("no masks")?,
        ds.sampling_masks.take().ok_or("no sampling masks")?,
    );
    let cams = ds.img_pose_indices.take().ok_or("no cameras")?;
    let mut imgs = Array3::<u8>::zeros((n, hw, 3));
    let mut masks = Array3::<u8>::zeros((n, hw, 1));
    let mut sampling = Array3::<u8>::zeros((n, hw, 1));
    for i in 0..n {
        let v = i % views;
        imgs.slice_mut(s![i, .., ..])
            .assign(&src_i.slice(s![v, .., ..]));
        masks
            .slice_mut(s![i, .., ..])
            .assign(&src_m.slice(s![v, .., ..]));
        sampling
            .slice_mut(s![i, .., ..])
            .assign(&src_s.slice(s![v, .., ..]));
    }
    drop((src_i, src_m, src_s));
    ds.imgs = Some(imgs);
    ds.masks = Some(masks);
    ds.sampling_masks = Some(sampling);
    ds.img_shape = Some([n, res, res, 3]);
    ds.kp_idxs = Some(Array1::zeros(n));
    ds.img_pose_indices = Some(Array1::from_iter((0..n).map(|i| cams[i % views])));
    ds.bkgd_idxs = Some(Array1::zeros(n));
    let t = Instant::now();
    ds.write(
        out,
        &WriteOptions {
            compression: Compression::Stored,
        },
    )?;
    println!(
        "wrote {n} images to {out} ({} bytes) in {:.1} s",
        std::fs::metadata(out)?.len(),
        t.elapsed().as_secs_f64()
    );
    Ok(())
}
