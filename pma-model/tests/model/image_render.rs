//! Whole-image rendering with a mock chunk renderer whose output is a known function of the
//! ray direction and the background it is handed: the scatter must put every value at its
//! pixel, leave everything outside the body box untouched, and not depend on the chunk size.

// The mock renderers return the crate's `Result`, whose error type is large; boxing it here
// would not match the `ChunkRenderer` signature.
#![allow(clippy::result_large_err)]

use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};

use candle_core::{Device, Tensor};
use pma_data::camera::Camera;
use pma_data::cylinder::{cylinder_box, cylinder_from_joints, CylinderParams, HeadDir};
use pma_data::skeleton::Joints;
use pma_model::error::Result;
use pma_model::render::image::{body_box, render_image, ChunkRender, ImageOptions, RenderedImage};

const W: usize = 64;
const H: usize = 48;
const F: f32 = 60.0;

/// Camera at (0, -0.9, 4) looking along world -z (identity rotation), so the world ray
/// direction of pixel (x, y) is ((x - cx)/f, -(y - cy)/f, -1).
fn camera() -> Camera {
    let c2w = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, -0.9],
        [0.0, 0.0, 1.0, 4.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    Camera::new(W, H, F, F, 32.0, 24.0, c2w).unwrap()
}

/// A standing figure around the origin: head toward -y, feet at y = 0.
fn joints(shift_x: f32) -> Joints {
    let mut kp = [[0.0f32; 3]; 24];
    for (j, k) in kp.iter_mut().enumerate() {
        let a = j as f32 * 0.7;
        *k = [
            shift_x + 0.3 * a.sin(),
            -1.7 * j as f32 / 23.0,
            0.1 * a.cos(),
        ];
    }
    kp
}

fn background() -> Vec<f32> {
    (0..H * W * 3)
        .map(|i| ((i * 37) % 101) as f32 / 100.0)
        .collect()
}

/// The mock's colour for a ray direction (before mixing with the background).
fn colour(d: [f32; 3]) -> [f32; 3] {
    [
        0.5 + 0.5 * d[0],
        0.5 + 0.5 * d[1],
        0.25 * (d[0] * d[0] + d[1] * d[1]),
    ]
}

/// Mock renderer: rgb = ½·colour(d) + ½·bg, acc = ¼ + ½|d_x|, disp = 1 + d_y. Counts rays and
/// checks that directions are unnormalised (camera-space z = -1, here world z) and that all
/// rays start at the camera.
fn mock<'a>(
    rays: &'a AtomicUsize,
    calls: &'a AtomicUsize,
) -> impl Fn(&Tensor, &Tensor, &Tensor) -> Result<ChunkRender> + Sync + 'a {
    move |o: &Tensor, d: &Tensor, bg: &Tensor| {
        let n = d.dims()[0];
        rays.fetch_add(n, Relaxed);
        calls.fetch_add(1, Relaxed);
        let (o, d, bg) = (
            o.to_vec2::<f32>()?,
            d.to_vec2::<f32>()?,
            bg.to_vec2::<f32>()?,
        );
        let mut rgb = Vec::with_capacity(3 * n);
        let (mut acc, mut disp) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for i in 0..n {
            assert_eq!(o[i], vec![0.0, -0.9, 4.0], "ray origin");
            assert_eq!(
                d[i][2], -1.0,
                "direction not in the unnormalised render convention"
            );
            let c = colour([d[i][0], d[i][1], d[i][2]]);
            rgb.extend((0..3).map(|k| 0.5 * c[k] + 0.5 * bg[i][k]));
            acc.push(0.25 + 0.5 * d[i][0].abs());
            disp.push(1.0 + d[i][1]);
        }
        let dev = Device::Cpu;
        Ok(ChunkRender {
            rgb: Tensor::from_vec(rgb, (n, 3), &dev)?,
            acc: Tensor::from_vec(acc, n, &dev)?,
            disp: Tensor::from_vec(disp, n, &dev)?,
            stats: Default::default(),
        })
    }
}

fn render(kp: &Joints, chunk: usize, bg: Option<&[f32]>) -> (RenderedImage, usize, usize) {
    let (rays, calls) = (AtomicUsize::new(0), AtomicUsize::new(0));
    let opts = ImageOptions {
        chunk,
        ..ImageOptions::default()
    };
    let img = render_image(&mock(&rays, &calls), &camera(), kp, bg, &opts).unwrap();
    (img, rays.into_inner(), calls.into_inner())
}

#[test]
fn pixels_inside_the_box_get_the_renderer_output_and_the_rest_the_background() {
    let kp = joints(0.0);
    let bg = background();
    let (img, rays, calls) = render(&kp, 100, Some(&bg));
    let cam = camera();
    // The render box comes from the a = 1.6, b = 1.1 cylinder; the exclusive bottom-right bound
    // means columns x0..x1-1 and rows y0..y1-1.
    let cyl = cylinder_from_joints(&kp, &CylinderParams::render(HeadDir::NegY));
    let b = cylinder_box(&cyl, &cam, None).unwrap();
    assert!(
        b.x0 > 0 && b.y0 > 0 && (b.x1 as usize) < W - 1 && (b.y1 as usize) < H - 1,
        "box {b:?} should lie inside"
    );
    assert!(
        b.width() >= 10 && b.height() >= 20,
        "box {b:?} too small to be a useful test"
    );
    assert_eq!(rays, b.width() * b.height());
    assert_eq!(calls, rays.div_ceil(100));
    assert_eq!((img.width, img.height), (W, H));
    for y in 0..H {
        for x in 0..W {
            let p = y * W + x;
            let got = &img.rgb[3 * p..3 * p + 3];
            let bgp = &bg[3 * p..3 * p + 3];
            if b.contains(x, y) {
                let d = [(x as f32 - 32.0) / F, -(y as f32 - 24.0) / F, -1.0];
                let c = colour(d);
                for k in 0..3 {
                    let want = 0.5 * c[k] + 0.5 * bgp[k];
                    assert!(
                        (got[k] - want).abs() <= 1e-6,
                        "pixel ({x},{y}) channel {k}: {} vs {want}",
                        got[k]
                    );
                }
                assert!(
                    (img.acc[p] - (0.25 + 0.5 * d[0].abs())).abs() <= 1e-6,
                    "acc at ({x},{y})"
                );
                assert!(
                    (img.disp[p] - (1.0 + d[1])).abs() <= 1e-6,
                    "disp at ({x},{y})"
                );
            } else {
                assert_eq!(got, bgp, "pixel ({x},{y}) outside the box");
                assert_eq!(
                    (img.acc[p], img.disp[p]),
                    (0.0, 0.0),
                    "pixel ({x},{y}) outside the box"
                );
            }
        }
    }
}

#[test]
fn chunk_size_does_not_change_the_image() {
    let kp = joints(0.0);
    let bg = background();
    let (reference, rays, _) = render(&kp, 5120, Some(&bg));
    assert!(rays > 13, "need more rays than the odd chunk sizes below");
    for chunk in [1, 7, 13, rays - 1, rays] {
        let (img, _, calls) = render(&kp, chunk, Some(&bg));
        assert_eq!(calls, rays.div_ceil(chunk), "chunk {chunk}");
        assert!(img == reference, "chunk {chunk} changed the image");
    }
}

#[test]
fn body_outside_the_view_gives_the_background_without_rendering() {
    // Far to the side: every cap point projects left of the image, the clipped box is empty.
    let kp = joints(-40.0);
    let bg = background();
    assert!(body_box(&camera(), &kp, HeadDir::NegY).is_empty());
    let (img, rays, calls) = render(&kp, 64, Some(&bg));
    assert_eq!((rays, calls), (0, 0));
    assert_eq!(img.rgb, bg);
    assert!(img.acc.iter().chain(&img.disp).all(|&v| v == 0.0));
    // No background given: black.
    let (img, _, _) = render(&kp, 64, None);
    assert!(img.rgb.iter().all(|&v| v == 0.0));
}

#[test]
fn body_around_the_camera_renders_the_whole_frame() {
    // Part of the cylinder behind the camera: its projection is meaningless, so every pixel
    // is traced instead of a wrong box.
    let mut kp = joints(0.0);
    for k in kp.iter_mut() {
        k[2] += 4.0;
    }
    let (_, rays, _) = render(&kp, 512, None);
    assert_eq!(rays, W * H);
}

#[test]
fn bad_inputs_are_errors() {
    let kp = joints(0.0);
    let cam = camera();
    let (rays, calls) = (AtomicUsize::new(0), AtomicUsize::new(0));
    let opts = ImageOptions {
        chunk: 0,
        ..ImageOptions::default()
    };
    assert!(render_image(&mock(&rays, &calls), &cam, &kp, None, &opts).is_err());
    let opts = ImageOptions::default();
    let short = vec![0.0f32; W * H * 3 - 1];
    let msg = render_image(&mock(&rays, &calls), &cam, &kp, Some(&short), &opts)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("background"), "{msg}");
    let mut nan = kp;
    nan[5][1] = f32::NAN;
    let msg = render_image(&mock(&rays, &calls), &cam, &nan, None, &opts)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("joint 5"), "{msg}");
    // A renderer that returns the wrong number of values is caught, not scattered.
    let wrong = |_: &Tensor, d: &Tensor, _: &Tensor| -> Result<ChunkRender> {
        let n = d.dims()[0];
        let dev = Device::Cpu;
        Ok(ChunkRender {
            rgb: Tensor::zeros((n, 3), candle_core::DType::F32, &dev)?,
            acc: Tensor::zeros(n + 1, candle_core::DType::F32, &dev)?,
            disp: Tensor::zeros(n, candle_core::DType::F32, &dev)?,
            stats: Default::default(),
        })
    };
    let msg = render_image(&wrong, &cam, &kp, None, &opts)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("chunk acc"), "{msg}");
    assert_eq!(rays.load(Relaxed), 0, "the renderer ran on invalid input");
}
