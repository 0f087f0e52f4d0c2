//! Parity with the official reference: every stage of the golden forward pass
//! (fixtures/golden, produced by the unmodified PyTorch code on CPU in float32).
//!
//! Tolerance: max abs error ≤ 1e-4, or ≤ 1e-4 relative to |reference| where values exceed 1
//! (depths and disparities of several metres, frequencies γ ≈ 30, pre-activations).

use crate::common::*;

fn check_case(dir: &str, sigma_override: bool) {
    let case = GoldenCase::load(dir, sigma_override);
    let mut trace = pma_model::render::avatar::Trace::default();
    let out = case.forward(Some(&mut trace));
    let g = &case.golden;
    let s_c = case.avatar.config().n_samples;
    let s_f = case.avatar.config().n_importance;
    let sub = case.subset_rays();
    let mut report = Report::default();

    // Ray casting.
    let bounds = out.bounds.as_ref().expect("cast on the host");
    let near: Vec<f32> = bounds.near.clone();
    let far: Vec<f32> = bounds.far.clone();
    report.cmp("raycast/near", &near, &g.f32("raycast/near"));
    report.cmp("raycast/far", &far, &g.f32("raycast/far"));
    report.cmp(
        "raycast/z_vals_coarse",
        &flat(&out.z_coarse),
        &g.f32("raycast/z_vals_coarse"),
    );
    for key in [
        "raycast/pts_coarse",
        "raycast/pts_is",
        "raycast/z_vals_merged",
    ] {
        report.cmp(key, &flat(&trace.tensors[key]), &g.f32(key));
    }
    let perm: Vec<f32> = flat(
        &trace.tensors["raycast/sorted_idxs"]
            .to_dtype(candle_core::DType::F32)
            .unwrap(),
    );
    report.cmp(
        "raycast/sorted_idxs",
        &perm,
        &g.i64_as_f32("raycast/sorted_idxs"),
    );

    // Network stages, coarse and fine.
    for (stage, s) in [("coarse", s_c), ("fine", s_f)] {
        let t = |k: &str| trace.tensors[&format!("{stage}/{k}")].clone();
        if g.has(&format!("{stage}/pose6d")) {
            for k in [
                "pose6d",
                "gnn_layer0_pre_sin",
                "gnn_layer1_pre_sin",
                "gnn_layer2_pre_sin",
                "gnn_layer3_pre_sin",
                "gnn_feat",
                "axis_scale",
                "win_layer_pose",
            ] {
                report.cmp(
                    &format!("{stage}/{k}"),
                    &flat(&t(k)),
                    &g.f32(&format!("{stage}/{k}")),
                );
            }
            // Full-size per-point arrays.
            report.cmp(
                &format!("{stage}/sigma_raw"),
                &flat(&t("sigma_raw")),
                &g.f32(&format!("{stage}/sigma_raw")),
            );
            report.cmp(
                &format!("{stage}/rgb_logits"),
                &flat(&t("rgb_logits")),
                &g.f32(&format!("{stage}/rgb_logits")),
            );
            report.cmp(
                &format!("{stage}/view_dir_root"),
                &flat(&t("view_dir_root")),
                &g.f32(&format!("{stage}/view_dir_root")),
            );
            // SUBSET arrays: rows ray*S + s of the subset rays.
            for k in [
                "pts_jt",
                "pts_t",
                "x_bar",
                "w_p",
                "pts_enc_pose",
                "win_maxpool",
                "win_logits",
                "w_f",
                "w",
                "f_m",
                "pts_enc_point",
                "modulator_out",
                "density_l0_pre_relu",
                "density_feat",
                "feature_linear",
                "view_l0_pre_relu",
            ] {
                report.cmp(
                    &format!("{stage}/{k}"),
                    &flat(&subset_rows(&t(k), &sub, s)),
                    &g.f32(&format!("{stage}/{k}")),
                );
            }
            for k in ["mod_freq", "mod_phase"] {
                report.cmp(
                    &format!("{stage}/{k}"),
                    &flat(&subset_rows_dim1(&t(k), &sub, s)),
                    &g.f32(&format!("{stage}/{k}")),
                );
            }
            // View SH and frame codes: per-ray features broadcast over samples.
            let view = trace.tensors["view_features"].clone();
            let sh = view.narrow(1, 0, 16).unwrap();
            let codes = view.narrow(1, 16, view.dim(1).unwrap() - 16).unwrap();
            report.cmp(
                &format!("{stage}/view_sh"),
                &flat(&per_sample(&sh, &sub, s)),
                &g.f32(&format!("{stage}/view_sh")),
            );
            report.cmp(
                &format!("{stage}/framecodes"),
                &flat(&per_sample(&codes, &sub, s)),
                &g.f32(&format!("{stage}/framecodes")),
            );
        }
    }

    // Rendering.
    for (name, r) in [("render_coarse", &out.coarse), ("render_fine", &out.fine)] {
        report.cmp(
            &format!("{name}/rgb_map"),
            &flat(&r.rgb),
            &g.f32(&format!("{name}/rgb_map")),
        );
        report.cmp(
            &format!("{name}/acc_map"),
            &flat(&r.acc),
            &g.f32(&format!("{name}/acc_map")),
        );
        report.cmp(
            &format!("{name}/disp_map"),
            &flat(&r.disp),
            &g.f32(&format!("{name}/disp_map")),
        );
        report.cmp(
            &format!("{name}/weights"),
            &flat(&r.weights),
            &g.f32(&format!("{name}/weights")),
        );
        report.cmp(
            &format!("{name}/alpha"),
            &flat(&r.alpha),
            &g.f32(&format!("{name}/alpha")),
        );
        report.cmp(
            &format!("{name}/depth_map"),
            &flat(&r.depth),
            &g.f32(&format!("{name}/depth_map")),
        );
    }
    report.cmp(
        "render_coarse/raw",
        &flat(&out.raw_coarse),
        &g.f32("render_coarse/raw"),
    );
    report.cmp(
        "render_fine/raw",
        &flat(&out.raw),
        &g.f32("render_fine/raw"),
    );
    report.cmp(
        "render_fine/z_vals",
        &flat(&out.z_vals),
        &g.f32("render_fine/z_vals"),
    );
    report.cmp("out/rgb_map", &flat(&out.fine.rgb), &g.f32("out/rgb_map"));
    report.cmp("out/rgb0", &flat(&out.coarse.rgb), &g.f32("out/rgb0"));
    report.cmp("out/acc_map", &flat(&out.fine.acc), &g.f32("out/acc_map"));
    report.cmp("out/acc0", &flat(&out.coarse.acc), &g.f32("out/acc0"));
    report.cmp(
        "out/disp_map",
        &flat(&out.fine.disp),
        &g.f32("out/disp_map"),
    );
    report.cmp("out/disp0", &flat(&out.coarse.disp), &g.f32("out/disp0"));
    report.cmp("out/T_i", &flat(&out.fine.weights), &g.f32("out/T_i"));
    report.cmp("out/alpha", &flat(&out.fine.alpha), &g.f32("out/alpha"));
    report.cmp("out/alpha0", &flat(&out.coarse.alpha), &g.f32("out/alpha0"));
    report.cmp(
        "out/vol_scale",
        &flat(&out.vol_scale),
        &g.f32("out/vol_scale"),
    );
    report.finish(dir);
}

#[test]
fn standard_case_matches_reference_at_every_stage() {
    check_case("golden", false);
}

#[test]
fn dense_case_matches_reference_at_every_stage() {
    check_case("golden/dense", true);
}
