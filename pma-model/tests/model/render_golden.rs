//! `raw2outputs` against the reference's coarse (48 samples) and fine (72 merged samples)
//! renders, standard and dense cases. Inputs are the reference's own raw outputs, z values,
//! ray directions and backgrounds.

use std::collections::HashMap;

use crate::common::{flat, load_golden, max_abs_err};
use candle_core::Tensor;
use pma_model::render::volume::raw2outputs;

/// Max abs error allowed against the reference's float32 outputs.
const TOL: f32 = 1e-4;

fn get<'a>(g: &'a HashMap<String, Tensor>, key: &str) -> &'a Tensor {
    g.get(key)
        .unwrap_or_else(|| panic!("golden key {key} missing"))
}

fn assert_close(what: &str, got: &Tensor, want: &Tensor) {
    assert_eq!(got.dims(), want.dims(), "{what}: shape");
    let err = max_abs_err(&flat(got), &flat(want));
    eprintln!("{what}: max abs err {err:e}");
    assert!(err <= TOL, "{what}: max abs error {err} > {TOL}");
}

fn check(case: &str, stage: &str) {
    let g = load_golden(&format!("{case}golden.safetensors"));
    let p = |k: &str| format!("{stage}/{k}");
    let out = raw2outputs(
        get(&g, &p("raw")),
        get(&g, &p("z_vals")),
        get(&g, "input/rays_d"),
        Some(get(&g, "input/bgs")),
    )
    .unwrap();
    let n = get(&g, "input/rays_d").dims()[0];
    let what = |k: &str| format!("{case}{stage}/{k}");
    assert_close(&what("rgb_map"), &out.rgb, get(&g, &p("rgb_map")));
    assert_close(
        &what("acc_map"),
        &out.acc,
        &get(&g, &p("acc_map")).reshape(n).unwrap(),
    );
    assert_close(
        &what("disp_map"),
        &out.disp,
        &get(&g, &p("disp_map")).reshape(n).unwrap(),
    );
    assert_close(
        &what("depth_map"),
        &out.depth,
        &get(&g, &p("depth_map")).reshape(n).unwrap(),
    );
    assert_close(&what("weights"), &out.weights, get(&g, &p("weights")));
    assert_close(&what("alpha"), &out.alpha, get(&g, &p("alpha")));
}

#[test]
fn coarse_standard() {
    check("", "render_coarse");
}

#[test]
fn fine_standard() {
    check("", "render_fine");
}

#[test]
fn coarse_dense() {
    check("dense/", "render_coarse");
}

#[test]
fn fine_dense() {
    check("dense/", "render_fine");
}

/// The dense case is the one with weight spread over many samples; check it really is, so the
/// comparisons above exercise the transmittance product and not only the last sample.
#[test]
fn dense_case_is_not_degenerate() {
    let g = load_golden("dense/golden.safetensors");
    let w = flat(get(&g, "render_fine/weights"));
    let m = get(&g, "render_fine/weights").dims()[1];
    let spread = w
        .chunks(m)
        .filter(|row| row.iter().filter(|&&x| x > 1e-3).count() >= 3)
        .count();
    assert!(
        spread >= 8,
        "only {spread} rays have weight on >= 3 samples"
    );
}
