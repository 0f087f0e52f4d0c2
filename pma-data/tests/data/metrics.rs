//! PSNR / SSIM (docs/conventions.md, "Evaluation protocol") against scikit-image and closed forms.
//!
//! The scikit-image numbers come from `fixtures/metrics/skimage_reference.py`
//! (scikit-image 0.26.0, numpy 2.4), which builds the same closed-form arrays.

// The reference numbers are pasted exactly as the script prints them.
#![allow(clippy::excessive_precision)]

use pma_data::metrics::{
    psnr, psnr_masked, quantize, score_image, ssim, ssim_masked, tight_box, Region, TightBox,
};

const H: usize = 12;
const W: usize = 10;

/// The script's `a`, `b` (channels last, f32) and elliptic mask.
fn arrays() -> (Vec<f32>, Vec<f32>, Vec<u8>) {
    let (mut a, mut b, mut m) = (Vec::new(), Vec::new(), Vec::new());
    for y in 0..H {
        for x in 0..W {
            for c in 0..3 {
                a.push(((7 * y + 3 * x + 5 * c) % 11) as f32 / 10.0);
                b.push(((5 * y + x * x + 2 * c) % 13) as f32 / 12.0);
            }
            let (dy, dx) = (y as f64 - 5.0, x as f64 - 4.0);
            m.push((dy * dy / 16.0 + dx * dx / 9.0 <= 1.0) as u8);
        }
    }
    (a, b, m)
}

fn f64s(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| x as f64).collect()
}

fn close(got: f64, want: f64, tol: f64) {
    assert!((got - want).abs() <= tol, "got {got:.15}, want {want:.15}");
}

#[test]
fn psnr_matches_scikit_image_and_numpy() {
    let (a, b, m) = arrays();
    close(psnr(&a, &b).unwrap(), 7.123122950506070, 1e-9);
    close(
        psnr_masked(&a, &b, &m, H, W, Region::Mask)
            .unwrap()
            .unwrap(),
        7.189967141425594,
        1e-9,
    );
    close(
        psnr_masked(&a, &b, &m, H, W, Region::Bbox)
            .unwrap()
            .unwrap(),
        7.485813989685001,
        1e-9,
    );
    assert_eq!(
        tight_box(&m, H, W),
        Some(TightBox {
            y0: 1,
            x0: 1,
            y1: 10,
            x1: 8
        })
    );
}

#[test]
fn ssim_matches_scikit_image() {
    let (a, b, m) = arrays();
    close(
        ssim(&f64s(&a), &f64s(&b), H, W, 2.0).unwrap(),
        0.071512451272593,
        1e-12,
    );
    close(
        ssim(&f64s(&a), &f64s(&b), H, W, 1.0).unwrap(),
        0.059107835293989,
        1e-12,
    );
    // On the tight box (9x7, no growth needed), with the reference's data range.
    close(
        ssim_masked(&b, &a, &m, H, W, 2.0).unwrap().unwrap(),
        0.108438899927551,
        1e-12,
    );
}

#[test]
fn closed_form_cases() {
    // A constant offset of 0.25 everywhere: MSE 1/16.
    let gt = vec![0.5f32; 3 * 64];
    let pred = vec![0.75f32; 3 * 64];
    close(
        psnr(&pred, &gt).unwrap(),
        -10.0 * (1.0f64 / 16.0).log10(),
        1e-12,
    );
    assert_eq!(psnr(&gt, &gt).unwrap(), f64::INFINITY);
    // Identical images: SSIM 1 for any data range.
    let (a, _, _) = arrays();
    for dr in [1.0, 2.0] {
        close(ssim(&f64s(&a), &f64s(&a), H, W, dr).unwrap(), 1.0, 1e-12);
    }
    // Constant images (zero variance): SSIM reduces to (2ab + C1) / (a² + b² + C1).
    let (x, y) = (0.5f64, 0.25f64);
    let c1 = (0.01f64 * 2.0).powi(2);
    close(
        ssim(&vec![x; 7 * 7 * 3], &vec![y; 7 * 7 * 3], 7, 7, 2.0).unwrap(),
        (2.0 * x * y + c1) / (x * x + y * y + c1),
        1e-12,
    );
    // Error on foreground pixels only: the mask PSNR sees it all, the box less.
    let mut mask = vec![0u8; 64];
    for i in [9, 10, 17, 18, 19, 26] {
        mask[i] = 1;
    }
    let pred: Vec<f32> = (0..3 * 64)
        .map(|i| if mask[i / 3] > 0 { 0.75 } else { 0.5 })
        .collect();
    close(
        psnr_masked(&pred, &gt, &mask, 8, 8, Region::Mask)
            .unwrap()
            .unwrap(),
        -10.0 * (1.0f64 / 16.0).log10(),
        1e-12,
    );
    // Box rows 1..4, cols 1..4: 9 pixels, 6 of them wrong.
    close(
        psnr_masked(&pred, &gt, &mask, 8, 8, Region::Bbox)
            .unwrap()
            .unwrap(),
        -10.0 * (6.0f64 / 9.0 / 16.0).log10(),
        1e-12,
    );
}

#[test]
fn empty_masks_small_crops_and_bad_sizes() {
    let (a, b, _) = arrays();
    assert_eq!(
        score_image(&a, &b, &[0; H * W], H, W, Region::Mask, 2.0).unwrap(),
        None
    );
    // A 1-pixel mask: the SSIM crop grows to 7x7 inside the image.
    let mut one = vec![0u8; H * W];
    one[0] = 1;
    let (p, s) = score_image(&a, &b, &one, H, W, Region::Mask, 2.0)
        .unwrap()
        .unwrap();
    assert!(p.is_finite() && s.is_finite());
    let want = ssim_masked(&a, &b, &one, H, W, 2.0).unwrap().unwrap();
    let crop = |img: &[f32]| -> Vec<f64> {
        (0..7)
            .flat_map(|y| (0..7).flat_map(move |x| (0..3).map(move |c| (y, x, c))))
            .map(|(y, x, c)| img[3 * (y * W + x) + c] as f64)
            .collect()
    };
    close(ssim(&crop(&a), &crop(&b), 7, 7, 2.0).unwrap(), want, 1e-15);
    assert!(ssim(&f64s(&a), &f64s(&b), 6, W, 2.0).is_err());
    assert!(psnr(&a, &b[1..]).is_err());
    assert!(psnr_masked(&a, &b, &one[1..], H, W, Region::Mask).is_err());
}

#[test]
fn quantization_truncates_like_the_reference() {
    assert_eq!(
        quantize(&[1.001, -0.001, 0.5, 0.99999]),
        vec![1.0, 0.0, 127.0 / 255.0, 254.0 / 255.0]
    );
}
