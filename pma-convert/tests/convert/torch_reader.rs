//! The restricted pickle reader against the golden checkpoint and the
//! hand-built fixtures of fixtures/convert/gen_torch_fixtures.py.

use crate::support::{f32s, fixture, root};

use pma_convert::{
    torch::{read_reference_checkpoint, TorchArchive},
    ConvertError,
};
use safetensors::{Dtype, SafeTensors};

#[test]
fn golden_ckpt_tensors_are_byte_identical_to_model_safetensors() {
    let ck = read_reference_checkpoint(&root().join("fixtures/golden/ckpt.th")).unwrap();
    let st_bytes = std::fs::read(root().join("fixtures/golden/model.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&st_bytes).unwrap();
    assert_eq!(ck.model.len(), 71);
    assert_eq!(st.len(), 71);
    for (name, t) in &ck.model {
        let view = st
            .tensor(name)
            .unwrap_or_else(|_| panic!("{name} missing from model.safetensors"));
        assert_eq!(t.dtype, view.dtype(), "{name}");
        assert_eq!(t.shape, view.shape(), "{name}");
        assert!(t.data == view.data(), "{name}: bytes differ");
    }
    // State-dict order is the reference's module registration order
    // (docs/reference.md, "Checkpoint and state_dict names").
    assert_eq!(ck.model[0].0, "rest_pose");
    assert_eq!(ck.model[1].0, "pts_embedder.transforms");
    assert_eq!(
        ck.model.last().unwrap().0,
        "pose_extractor.sin_lin3.layer.bias"
    );
    assert_eq!(ck.global_iter, Some(0));
    let opt = ck.optimizer.expect("optimizer");
    assert!(opt.state.is_empty());
    assert_eq!(opt.param_groups.len(), 2);
    assert_eq!(opt.param_groups[0].lr, 1e-4);
    assert_eq!(opt.param_groups[1].lr, 5e-4);
    assert_eq!(opt.param_groups[0].params, (0..39).collect::<Vec<_>>());
    assert_eq!(opt.param_groups[1].params, (39..64).collect::<Vec<_>>());
    assert_eq!(opt.param_groups[1].betas, (0.9, 0.999));
    assert_eq!(opt.param_groups[1].eps, 1e-8);
}

#[test]
fn views_into_shared_storage_int64_and_number_steps() {
    let ck = read_reference_checkpoint(&fixture("tiny_views.th")).unwrap();
    let names: Vec<&str> = ck.model.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["a", "b", "c"]);
    assert_eq!(f32s(&ck.model[0].1.data), [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    assert_eq!(f32s(&ck.model[1].1.data), [6.0, 7.0, 8.0, 9.0, 10.0, 11.0]);
    assert_eq!(ck.model[1].1.shape, [2, 3]);
    let c = &ck.model[2].1;
    assert_eq!(c.dtype, Dtype::I64);
    let longs: Vec<i64> = c
        .data
        .chunks_exact(8)
        .map(|b| i64::from_le_bytes(b.try_into().unwrap()))
        .collect();
    assert_eq!(longs, [-3, 0, 7, 1 << 40]);
    assert_eq!(ck.global_iter, Some(7));
    let opt = ck.optimizer.unwrap();
    assert_eq!(opt.state[&0].step, 3.0);
    assert_eq!(opt.state[&1].step, 5.0);
    assert_eq!(f32s(&opt.state[&1].exp_avg.data), [0.25, 0.75]);
    assert_eq!(f32s(&opt.state[&1].exp_avg_sq.data), [0.5, -0.5]);
}

#[test]
fn non_contiguous_tensor_is_rejected() {
    let err = read_reference_checkpoint(&fixture("noncontig.th")).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, ConvertError::Invalid { .. }), "{msg}");
    assert!(
        msg.contains("model.t") && msg.contains("not contiguous"),
        "{msg}"
    );
}

#[test]
fn forbidden_global_is_refused_with_its_name_and_offset() {
    let err = TorchArchive::open(&fixture("evil_global.th"))
        .err()
        .expect("must fail");
    let msg = err.to_string();
    match err {
        ConvertError::ForbiddenGlobal {
            module,
            name,
            offset,
            ..
        } => {
            assert_eq!((module.as_str(), name.as_str()), ("posix", "system"));
            assert_eq!(offset, 17);
        }
        other => panic!("wrong error: {other}"),
    }
    assert!(
        msg.contains("posix.system") && msg.contains("evil_global.th"),
        "{msg}"
    );
}

#[test]
fn forbidden_opcode_is_refused_with_its_name_and_offset() {
    let err = TorchArchive::open(&fixture("evil_opcode.th"))
        .err()
        .expect("must fail");
    let msg = err.to_string();
    match err {
        ConvertError::ForbiddenOpcode {
            opcode,
            name,
            offset,
            ..
        } => {
            assert_eq!((opcode, name), (0x81, "NEWOBJ"));
            assert_eq!(offset, 45);
        }
        other => panic!("wrong error: {other}"),
    }
    assert!(msg.contains("NEWOBJ") && msg.contains("byte 45"), "{msg}");
}

#[test]
fn truncated_checkpoint_is_a_clear_error() {
    let bytes = std::fs::read(root().join("fixtures/golden/ckpt.th")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cut = dir.path().join("cut.th");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let err = read_reference_checkpoint(&cut).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, ConvertError::Zip { .. }), "{msg}");
    assert!(msg.contains("cut.th") && msg.contains("truncated"), "{msg}");
}

#[test]
fn a_file_that_is_not_a_zip_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("legacy.th");
    // Legacy torch files start with a pickle PROTO opcode.
    std::fs::write(&p, b"\x80\x02\x8a\x0al\xfc\x9cF\xf9 j\xa8P\x19.").unwrap();
    let msg = read_reference_checkpoint(&p).unwrap_err().to_string();
    assert!(msg.contains("legacy") && msg.contains("legacy.th"), "{msg}");
}
