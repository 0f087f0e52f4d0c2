//! Frequency histograms of the evaluation on a real textured image: the synthetic figure,
//! rendered by `pma_data::synth`, stands in for the ground truth; a blurred copy is a render
//! that lost its high frequencies, a relit copy one that kept them.

use glam::DVec3;
use pma_data::metrics::quantize;
use pma_data::skeleton::local_to_world;
use pma_data::synth;
use pma_model::eval::spectrum::{image_spectra, FREQ_BINS};

/// Separable Gaussian blur (clamped borders) of an `[h·w·3]` image.
fn blur(img: &[f32], h: usize, w: usize, sigma: f32) -> Vec<f32> {
    let r = (3.0 * sigma).ceil() as isize;
    let k: Vec<f32> = (-r..=r)
        .map(|i| (-((i * i) as f32) / (2.0 * sigma * sigma)).exp())
        .collect();
    let ks: f32 = k.iter().sum();
    let pass = |src: &[f32], dy: isize, dx: isize| -> Vec<f32> {
        let mut out = vec![0.0; src.len()];
        for y in 0..h as isize {
            for x in 0..w as isize {
                for c in 0..3 {
                    let mut s = 0.0;
                    for (j, kv) in k.iter().enumerate() {
                        let d = j as isize - r;
                        let yy = (y + d * dy).clamp(0, h as isize - 1) as usize;
                        let xx = (x + d * dx).clamp(0, w as isize - 1) as usize;
                        s += kv * src[3 * (yy * w + xx) + c];
                    }
                    out[3 * (y as usize * w + x as usize) + c] = s / ks;
                }
            }
        }
        out
    };
    pass(&pass(img, 0, 1), 1, 0)
}

fn figure_image(light: &synth::Light) -> (Vec<f32>, Vec<u8>, usize, usize) {
    let rest = synth::rest_pose();
    let fig = synth::Figure::new(&rest, 0);
    let walk = synth::walk_motion(&rest).unwrap();
    let f = 10;
    let root = walk.root[f].map(f64::from);
    let l2w = local_to_world(&rest, &walk.bones[f], DVec3::from(root));
    let cam = synth::ring_cameras(4, 160, 1, &synth::Ring::default()).unwrap()[0].clone();
    let r = synth::render(&fig, &l2w, &cam, light);
    let rgb = r.rgb.iter().map(|&v| v as f32 / 255.0).collect();
    (rgb, r.mask, cam.height, cam.width)
}

#[test]
fn a_blurred_render_is_further_from_the_ground_truth_than_a_sharp_one() {
    let (gt, mask, h, w) = figure_image(&synth::Light::default());
    assert!(
        mask.iter().filter(|&&m| m > 0).count() > 1000,
        "figure in view"
    );
    // Sharp but not identical: other lighting changes contrast and shading, not sharpness.
    let relit = synth::Light {
        ambient: 0.3,
        diffuse: 0.8,
        ..synth::Light::default()
    };
    let (sharp, _, _, _) = figure_image(&relit);
    let d = |render: &[f32]| image_spectra(render, &gt, &mask, h, w).unwrap().distance;
    let (d_same, d_sharp) = (d(&gt), d(&sharp));
    // Renders are scored 8-bit, as the evaluation writes them.
    let blurred = |sigma| quantize(&blur(&gt, h, w, sigma));
    let (d_blur1, d_blur2) = (d(&blurred(1.0)), d(&blurred(2.0)));
    assert_eq!(d_same, 0.0);
    assert!(
        d_blur1 > 2.0 * d_sharp && d_blur2 > d_blur1,
        "sharp {d_sharp}, blur σ1 {d_blur1}, blur σ2 {d_blur2}"
    );

    // The blurred render's histogram lies below the ground truth's at high frequencies.
    let s = image_spectra(&blurred(1.0), &gt, &mask, h, w).unwrap();
    let high = |p: &[f64]| p[FREQ_BINS / 2..].iter().sum::<f64>();
    assert!(high(&s.render) < 0.5 * high(&s.gt), "{:?}", s);
}
