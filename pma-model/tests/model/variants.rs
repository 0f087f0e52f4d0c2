//! The paper's ablations as model variants: each builds only the layers it uses, trains,
//! and round-trips through a checkpoint that names it.
#![cfg(feature = "train")]

use crate::train_support::*;
use candle_core::Device;
use pma_model::network::checkpoint;
use pma_model::network::config::Variant;
use pma_model::render::avatar::{Avatar, Mode};
use pma_model::train::{BatchSource, DatasetSource, Trainer};

/// Name prefixes of the tensors a variant must have (`true`) or must not have (`false`).
fn expected_prefixes(v: Variant) -> Vec<(&'static str, bool)> {
    let fw = v.feature_window();
    vec![
        ("graph_net.axis_scale", true),
        ("graph_net.layers.", v.gnn_features()),
        ("win_fun.layer_pose.", v.gnn_features()),
        ("win_fun.layer_point.", fw),
        ("win_fun.last_layer.", fw),
        ("pts_enc_pose.", fw),
        ("pts_enc_point.", v.synthesis()),
        ("modulator.", v.synthesis()),
        ("pose_extractor.", v.modulation()),
        ("pts_linears.0.weight", true),
    ]
}

#[test]
fn variants_hold_exactly_their_layers() {
    let rest = pma_data::synth::rest_pose();
    let mut counts = Vec::new();
    for v in Variant::ALL {
        let mut cfg = pma_model::Config::tiny();
        cfg.variant = v;
        let names: Vec<String> = checkpoint::tensor_layout(&cfg)
            .into_iter()
            .map(|s| s.name)
            .collect();
        for (prefix, present) in expected_prefixes(v) {
            let found = names.iter().any(|n| n.starts_with(prefix));
            assert_eq!(found, present, "{v}: tensors starting with `{prefix}`");
        }
        // A fresh avatar holds exactly the registered tensors.
        let a = Avatar::new(cfg.clone(), &rest, 1, &Device::Cpu).unwrap();
        let mut held: Vec<String> = a.tensors().into_keys().collect();
        held.sort();
        let mut want = names.clone();
        want.sort();
        assert_eq!(held, want, "{v}");
        counts.push((v, names.len()));
    }
    // Every ablation but `only-wf` leaves tensors out (w^p has no parameters, so dropping it
    // from the window changes the computation, not the tensor set).
    let full = counts[0].1;
    for (v, n) in &counts[1..] {
        match v {
            Variant::OnlyWf => assert_eq!(*n, full, "{v}"),
            _ => assert!(*n < full, "{v}: {n} tensors, full has {full}"),
        }
    }
}

#[test]
fn each_variant_trains_and_round_trips_through_a_checkpoint() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let probe = DatasetSource::new(data.clone(), 32, 2, true, 5, &Device::Cpu)
        .unwrap()
        .next_batch()
        .unwrap();
    for v in Variant::ALL {
        let mut run = tiny_run();
        run.model.variant = v;
        let mut t = Trainer::new(run, data.clone(), &Device::Cpu).unwrap();
        let before = param_bits(&t);
        for _ in 0..3 {
            let stats = t.step_read().unwrap();
            assert!(stats.skipped.is_none(), "{v}: step skipped");
        }
        let after = param_bits(&t);
        assert!(
            before.iter().zip(&after).any(|(a, b)| a.1 != b.1),
            "{v}: training changed no parameter"
        );
        let path = tmp.path().join(format!("{v}.safetensors"));
        t.avatar().save(&path).unwrap();
        let ck = checkpoint::load(&path, &Device::Cpu).unwrap();
        assert_eq!(ck.config.variant, v, "the checkpoint names its variant");
        let loaded = Avatar::from_tensors(ck.config, ck.tensors, &Device::Cpu).unwrap();
        let render = |a: &Avatar| -> Vec<u32> {
            let out = a
                .forward(
                    &probe.rays,
                    &probe.poses,
                    &mut Mode::Eval,
                    &Default::default(),
                    None,
                )
                .unwrap();
            bits(&out.fine.rgb)
        };
        let (a, b) = (render(t.avatar()), render(&loaded));
        assert!(!a.is_empty());
        assert_eq!(a, b, "{v}: round trip");
        // The same tensors under the config of a variant with other layers are refused.
        if !matches!(v, Variant::Full | Variant::OnlyWf) {
            let mut other = loaded.config().clone();
            other.variant = Variant::Full;
            let err = Avatar::from_tensors(other, loaded.tensors(), &Device::Cpu).unwrap_err();
            assert!(err.to_string().contains("missing tensor"), "{v}: {err}");
        }
    }
}
