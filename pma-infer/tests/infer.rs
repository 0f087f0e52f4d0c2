//! The inference-only binary renders a checkpoint to a PNG and fails cleanly on bad input.

use std::path::Path;
use std::process::{Command, Output};

use candle_core::Device;
use image::RgbImage;
use pma_model::render::avatar::Avatar;
use pma_model::Config;

fn infer(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pma-infer"))
        .args(args)
        .output()
        .expect("running pma-infer")
}

/// `pma-infer MODEL PNG 24 EXTRA...`, which must succeed: its output and the image written.
fn render_24(model: &Path, png: &Path, extra: &[&str]) -> (Output, RgbImage) {
    let args = [model.to_str().unwrap(), png.to_str().unwrap(), "24"];
    let out = infer(&[&args[..], extra].concat());
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    (out, image::open(png).unwrap().to_rgb8())
}

/// The largest difference of any channel of any pixel, in 8-bit levels.
fn max_level_diff(a: &RgbImage, b: &RgbImage) -> u8 {
    a.iter()
        .zip(b.iter())
        .map(|(x, y)| x.abs_diff(*y))
        .max()
        .unwrap()
}

#[test]
fn renders_one_png_and_rejects_bad_input() {
    let tmp = tempfile::tempdir().unwrap();
    let model = tmp.path().join("tiny.safetensors");
    // A fresh avatar whose density head is a constant 50: opaque wherever it is asked, so
    // the body must show up in the render (a random density head may be empty everywhere).
    let fresh = Avatar::new(
        Config::tiny(),
        &pma_data::synth::rest_pose(),
        2,
        &Device::Cpu,
    )
    .unwrap();
    let mut t = fresh.tensors();
    let w = t["sigma_linear.weight"].zeros_like().unwrap();
    t.insert("sigma_linear.weight".into(), w);
    let b = candle_core::Tensor::new(&[50f32], &Device::Cpu).unwrap();
    t.insert("sigma_linear.bias".into(), b);
    Avatar::from_tensors(fresh.config().clone(), t, &Device::Cpu)
        .unwrap()
        .save(&model)
        .unwrap();
    let png = tmp.path().join("out.png");
    let (out, img) = render_24(&model, &png, &[]);
    assert_eq!(image::image_dimensions(&png).unwrap(), (24, 24));
    assert!(String::from_utf8_lossy(&out.stdout).contains("render"));
    // The body is drawn over the black background: the corners stay black and the centre,
    // where the rest pose stands, does not.
    assert_eq!(img.get_pixel(0, 0).0, [0, 0, 0], "background corner");
    let lit = img.pixels().filter(|p| p.0 != [0, 0, 0]).count();
    assert!(lit > 0 && lit < 24 * 24, "{lit} non-black pixels");
    assert_ne!(img.get_pixel(12, 12).0, [0, 0, 0], "the body at the centre");

    // `--occupancy` needs a grid; with a never-refreshed one (every cell occupied) the
    // render is the same image.
    let out = infer(&[
        model.to_str().unwrap(),
        png.to_str().unwrap(),
        "24",
        "--occupancy",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.code() == Some(2) && err.contains("no occupancy grid"),
        "{err}"
    );
    let gridded = tmp.path().join("grid.safetensors");
    let grid = pma_model::network::occupancy::OccupancyGrid::new(Default::default()).unwrap();
    Avatar::load(&model, &Device::Cpu)
        .unwrap()
        .with_occupancy(Some(grid))
        .save(&gridded)
        .unwrap();
    let (_, gridded_img) = render_24(&gridded, &tmp.path().join("grid.png"), &["--occupancy"]);
    assert_eq!(gridded_img.into_raw(), img.clone().into_raw());

    // The body is opaque: stopping its rays once their transmittance is below 1e-3 leaves
    // out what is behind the surface, which the image weights by less than that.
    let (_, early) = render_24(
        &model,
        &tmp.path().join("early.png"),
        &["--early-stop", "1e-3"],
    );
    let worst = max_level_diff(&early, &img);
    assert!(worst <= 1, "early stop changed a pixel by {worst} levels");

    // Calls grouped by the joints their samples need: the same image up to float summation
    // order.
    let (_, grouped) = render_24(&model, &tmp.path().join("joints.png"), &["--cull-joints"]);
    let worst = max_level_diff(&grouped, &img);
    assert!(
        worst <= 1,
        "joint grouping changed a pixel by {worst} levels"
    );

    // Refused input exits with 2, naming what was wrong.
    let no_dir = tmp.path().join("missing").join("out.png");
    let (m, p) = (model.to_str().unwrap(), png.to_str().unwrap());
    for (args, needle) in [
        (vec![m], "usage"),
        (vec![m, p, "--cull"], "unknown flag \"--cull\""),
        (vec![m, p, "--device"], "--device needs a value"),
        (vec![m, p, "--device", "tpu"], "unknown device"),
        (vec![m, no_dir.to_str().unwrap(), "24"], "missing"),
        (vec![m, p, "--early-stop", "2"], "early_stop"),
        (vec![m, p, "--early-stop", "x"], "--early-stop needs"),
        (vec![m, p, "3"], "SIZE must be"),
        (vec!["/nonexistent.safetensors", p], "nonexistent"),
    ] {
        let out = infer(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.code() == Some(2) && err.contains(needle),
            "{args:?}: exit {:?}, {err}",
            out.status.code()
        );
        assert_eq!(err.lines().count(), 1, "{args:?}: {err}");
        assert!(!err.contains("panicked"));
    }
}
