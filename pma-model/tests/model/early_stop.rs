//! The early stop (`PassOptions::early_stop`): a ray's samples behind the depth where its
//! transmittance fell below the threshold skip the network. Nothing is left out when no ray
//! gets there; what is left out changes the coarse render by at most what the threshold
//! bounds; it is refused in training, with the grid-placed fine samples and out of (0, 1).

use crate::common::*;
use pma_model::render::avatar::{Mode, Outputs};
use pma_model::render::{Culling, PassOptions, SampleFill};

fn opts(early_stop: Option<f64>) -> PassOptions {
    PassOptions {
        culling: Culling {
            rays: true,
            sample_threshold: Some(0.0),
            sample_fill: SampleFill::Network,
        },
        early_stop,
        ..PassOptions::default()
    }
}

#[allow(clippy::result_large_err)]
fn infer(case: &GoldenCase, opts: &PassOptions) -> pma_model::error::Result<Outputs> {
    case.avatar
        .forward(&case.rays, &case.poses, &mut Mode::Infer, opts, None)
}

#[test]
fn early_stop_leaves_out_only_what_the_threshold_bounds() {
    let case = GoldenCase::load("golden/dense", true);
    let base = infer(&case, &opts(None)).unwrap();
    assert_eq!(base.stats.stopped_early, 0);

    // No ray's transmittance gets this low: the same samples run the network (in smaller
    // calls, so within f32 rounding of the pass without the stop).
    let never = infer(&case, &opts(Some(1e-30))).unwrap();
    println!("never: {:?}", never.stats);
    assert_eq!(never.stats.stopped_early, 0);
    assert_eq!(never.stats.coarse_evaluated, base.stats.coarse_evaluated);
    assert_eq!(never.stats.fine_evaluated, base.stats.fine_evaluated);
    for (a, b, name) in [
        (&base.fine.rgb, &never.fine.rgb, "rgb"),
        (&base.coarse.rgb, &never.coarse.rgb, "rgb0"),
        (&base.fine.acc, &never.fine.acc, "acc"),
    ] {
        let d = max_abs_diff(&flat(a), &flat(b));
        assert!(d <= 1e-5, "{name}: {d:e}");
    }

    // The golden model is faint (no ray's transmittance falls below 0.05); the same model
    // with a density head that is a constant 50 is opaque wherever a sample runs it.
    let mut t = case.avatar.tensors();
    let w = t["sigma_linear.weight"].zeros_like().unwrap();
    t.insert("sigma_linear.weight".into(), w);
    let b = t["sigma_linear.bias"]
        .ones_like()
        .unwrap()
        .affine(50.0, 0.0)
        .unwrap();
    t.insert("sigma_linear.bias".into(), b);
    let cfg = case.avatar.config().clone();
    let dev = case.avatar.device().clone();
    let opaque = GoldenCase {
        avatar: pma_model::render::avatar::Avatar::from_tensors(cfg, t, &dev).unwrap(),
        ..GoldenCase::load("golden/dense", true)
    };
    let opaque_base = infer(&opaque, &opts(None)).unwrap();
    for (case, base, eps) in [
        (&case, &base, 0.5),
        (&opaque, &opaque_base, 0.05),
        (&opaque, &opaque_base, 1e-3),
    ] {
        let early = infer(case, &opts(Some(eps))).unwrap();
        println!("eps {eps}: {:?} (without: {:?})", early.stats, base.stats);
        assert!(early.stats.stopped_early > 0, "eps {eps}: no ray stopped");
        // Coarse samples only go from evaluated to stopped.
        assert!(early.stats.coarse_evaluated < base.stats.coarse_evaluated);
        assert!(
            early.stats.coarse_evaluated + early.stats.stopped_early >= base.stats.coarse_evaluated
        );
        // Behind the stop the transmittance is below eps, so the coarse colour (samples
        // and background, both in [0, 1]) moves by at most 2·eps with or without what is
        // behind, and the opacity by at most eps; the margin is f32 rounding.
        let rgb = max_abs_diff(&flat(&base.coarse.rgb), &flat(&early.coarse.rgb));
        let acc = max_abs_diff(&flat(&base.coarse.acc), &flat(&early.coarse.acc));
        println!("eps {eps}: coarse rgb moved {rgb:e}, acc {acc:e}");
        assert!(
            rgb as f64 <= 2.0 * eps + 1e-5,
            "eps {eps}: rgb0 moved {rgb}"
        );
        assert!(acc as f64 <= eps + 1e-5, "eps {eps}: acc0 moved {acc}");
    }
}

#[test]
fn early_stop_is_refused_where_it_does_not_apply() {
    let case = GoldenCase::load("golden/dense", true);
    let err = case
        .avatar
        .forward(
            &case.rays,
            &case.poses,
            &mut Mode::Train(None),
            &opts(Some(1e-3)),
            None,
        )
        .unwrap_err();
    assert!(err.to_string().contains("early_stop"), "{err}");
    for bad in [0.0, 1.0, -1e-3, f64::NAN, f64::INFINITY] {
        let err = infer(&case, &opts(Some(bad))).unwrap_err();
        assert!(err.to_string().contains("early_stop"), "{bad}: {err}");
    }
    let with_grid_fine = PassOptions {
        occupancy: true,
        occupancy_fine: true,
        ..opts(Some(1e-3))
    };
    let err = with_grid_fine.validate(case.avatar.config()).unwrap_err();
    assert!(err.to_string().contains("early_stop"), "{err}");
}
