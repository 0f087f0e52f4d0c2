//! `pma convert checkpoint`: the golden reference checkpoint and the Adam
//! fixtures of fixtures/convert/gen_torch_fixtures.py.

use crate::support::{convert_fixture, f32s, root};

use candle_core::Device;
use pma_convert::{
    torch::read_reference_checkpoint,
    train_state::{reference_param_groups, sidecar_path, train_state_from_torch},
    ConvertError,
};
use pma_model::{
    error::ModelError,
    network::checkpoint::load,
    train::{state::fingerprint, TrainState},
    Config,
};
use safetensors::SafeTensors;

/// The generator's `pattern(seed, n, scale)`: `scale * (((k + seed) % 17) - 8)` rounded to f32.
fn pattern(seed: usize, n: usize, scale: f64) -> Vec<f32> {
    (0..n)
        .map(|k| (scale * (((k + seed) % 17) as f64 - 8.0)) as f32)
        .collect()
}

#[test]
fn golden_checkpoint_converts_to_identical_tensors_and_loads() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ref.safetensors");
    let rep = convert_fixture("golden/ckpt.th", &out, false).unwrap();
    assert_eq!(rep.n_tensors, 71);
    assert_eq!(rep.n_parameters, 3_111_524);
    assert!(rep.train_state.is_none());

    let golden = std::fs::read(root().join("fixtures/golden/model.safetensors")).unwrap();
    let golden = SafeTensors::deserialize(&golden).unwrap();
    let ours = std::fs::read(&out).unwrap();
    let (_, header) = SafeTensors::read_metadata(&ours).unwrap();
    let ours = SafeTensors::deserialize(&ours).unwrap();
    assert_eq!(ours.len(), golden.len());
    for (name, view) in golden.tensors() {
        let t = ours.tensor(&name).unwrap();
        assert_eq!(
            (t.dtype(), t.shape()),
            (view.dtype(), view.shape()),
            "{name}"
        );
        assert!(t.data() == view.data(), "{name}: bytes differ");
    }
    let meta = header.metadata().clone().unwrap();
    assert_eq!(meta["format"], "pma-checkpoint");
    assert_eq!(meta["n_framecodes"], "780");

    let ck = load(&out, &Device::Cpu).unwrap();
    let mut paper = Config::paper();
    paper.n_framecodes = 780;
    assert_eq!(ck.config, paper);
    assert!(!ck.meta.config_inferred);
    let rest = f32s(golden.tensor("rest_pose").unwrap().data());
    let flat: Vec<f32> = ck.meta.rest_pose.iter().flatten().copied().collect();
    assert_eq!(flat, rest);
}

#[test]
fn optimizer_ids_follow_the_reference_grouping() {
    let groups = reference_param_groups(&Config::paper());
    assert_eq!((groups[0].len(), groups[1].len()), (39, 25));
    // Spot checks of the optimiser ids (docs/reference.md, "Training schedule and Adam").
    let id = |i: usize| {
        if i < 39 {
            &groups[0][i]
        } else {
            &groups[1][i - 39]
        }
    };
    assert_eq!(id(0), "pts_enc_pose.sin_lin0.layer.weight");
    assert_eq!(id(4), "graph_net.axis_scale");
    assert_eq!(id(7), "graph_net.layers.0.lin.weight");
    assert_eq!(id(11), "graph_net.layers.2.weight");
    assert_eq!(id(21), "win_fun.layer_pose.layer.weight");
    assert_eq!(id(38), "pose_extractor.sin_lin3.layer.bias");
    assert_eq!(id(39), "pts_linears.0.weight");
    assert_eq!(id(55), "sigma_linear.weight");
    assert_eq!(id(57), "views_linears.0.weight");
    assert_eq!(id(59), "feature_linear.weight");
    assert_eq!(id(63), "framecodes.codes.weight");
}

#[test]
fn adam_state_is_exported_by_parameter_name_and_loads_in_the_trainer() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("resume.safetensors");
    let rep = convert_fixture("convert/ckpt_adam.th", &out, true).unwrap();
    let side = dir.path().join("resume.optim.safetensors");
    assert_eq!(rep.train_state.as_deref(), Some(side.as_path()));
    assert_eq!(sidecar_path(&out), side);
    assert_eq!(rep.n_moments, 64);
    assert_eq!(rep.global_iter, Some(1234));

    // Model tensors: large ones hold the generator's pattern, seeded by state_dict position.
    let bytes = std::fs::read(&out).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    assert_eq!(
        f32s(st.tensor("pts_linears.0.weight").unwrap().data()),
        pattern(7, 256 * 768, 1e-3)
    );

    let state = TrainState::load(&side, &Device::Cpu).unwrap();
    assert_eq!(state.global_iter, 1234);
    assert_eq!(state.model_fingerprint, Some(fingerprint(&bytes)));
    let names: Vec<&str> = state.groups.iter().map(|g| g.name.as_str()).collect();
    assert_eq!(names, ["freq", "other"]);
    assert_eq!(
        (state.groups[0].lr, state.groups[0].initial_lr),
        (9.4e-5, 1e-4)
    );
    assert_eq!(
        (state.groups[1].lr, state.groups[1].initial_lr),
        (4.7e-4, 5e-4)
    );
    assert_eq!(state.groups[1].betas, [0.9, 0.999]);
    assert_eq!(state.groups[0].params.len(), 39);
    assert_eq!(state.groups[1].params[24], "framecodes.codes.weight");
    assert_eq!(state.params.len(), 64);
    assert!(state.params.values().all(|m| m.step == 1234));
    // Moments are seeded by optimiser id: id 4 = graph_net.axis_scale, id 63 = framecodes.
    let axis = &state.params["graph_net.axis_scale"];
    assert_eq!(axis.exp_avg.dims(), [24, 3]);
    let flat = |t: &candle_core::Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert_eq!(flat(&axis.exp_avg), pattern(4, 72, 1e-4));
    let codes = &state.params["framecodes.codes.weight"];
    let sq: Vec<f32> = pattern(163, 780 * 128, 1e-7)
        .iter()
        .map(|v| v.abs())
        .collect();
    assert_eq!(flat(&codes.exp_avg_sq), sq);
}

#[test]
fn checkpoint_of_another_architecture_is_rejected_with_the_tensor_named() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bad.safetensors");
    let err = convert_fixture("convert/bad_config.th", &out, false).unwrap_err();
    let msg = err.to_string();
    assert!(
        matches!(&err, ConvertError::Model(e) if matches!(**e, ModelError::Checkpoint { .. })),
        "{msg}"
    );
    assert!(
        msg.contains("pts_linears.5.weight") && msg.contains("[256, 1000]"),
        "{msg}"
    );
    assert!(!out.exists());
}

#[test]
fn an_empty_adam_state_exports_zero_moments() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.safetensors");
    // The golden checkpoint's Adam has never stepped: every parameter starts from zero.
    let rep = convert_fixture("golden/ckpt.th", &out, true).unwrap();
    assert_eq!(rep.n_moments, 0);
    let state = TrainState::load(rep.train_state.as_ref().unwrap(), &Device::Cpu).unwrap();
    assert_eq!((state.groups[0].lr, state.groups[1].lr), (1e-4, 5e-4));
    assert_eq!(state.global_iter, 0);
    assert_eq!(state.params.len(), 64);
    let w = &state.params["pts_linears.5.weight"];
    assert_eq!((w.step, w.exp_avg.dims()), (0, &[256usize, 1024][..]));
    let max = w
        .exp_avg_sq
        .abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    assert_eq!(max, 0.0);
}

#[test]
fn optimizer_export_needs_the_optimizer_and_global_iter() {
    let mut ck = read_reference_checkpoint(&root().join("fixtures/golden/ckpt.th")).unwrap();
    let cfg = Config::paper();
    // The export is refused with the file and the missing entry named.
    let assert_refused = |ck: &_, missing: &str| {
        let msg = train_state_from_torch(ck, &cfg, None)
            .unwrap_err()
            .to_string();
        assert!(msg.contains("ckpt.th") && msg.contains(missing), "{msg}");
    };
    ck.global_iter = None;
    assert_refused(&ck, "global_iter");
    ck.global_iter = Some(5);
    ck.optimizer = None;
    assert_refused(&ck, "optimizer");
}

#[test]
fn a_pma_checkpoint_is_not_a_training_state() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.safetensors");
    convert_fixture("golden/ckpt.th", &out, false).unwrap();
    let msg = TrainState::load(&out, &Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("pma-train-state") && msg.contains("pma-checkpoint"),
        "{msg}"
    );
}
