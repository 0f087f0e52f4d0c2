//! Cameras, rays and cylinders against the reference's golden batch
//! (fixtures/golden, see its manifest.json): `input/rays_o`, `input/rays_d`
//! from `input/c2w` and `input/pixels` (H = W = 1000, focal 1145, centre
//! (500, 500), unit directions), and `input/cyls` from `input/kp3d`.

use std::path::PathBuf;

use pma_data::camera::Camera;
use pma_data::cylinder::{cylinder_from_joints, CylinderParams, HeadDir};
use pma_data::skeleton::{Joints, N_JOINTS};
use safetensors::SafeTensors;

use crate::support::max_abs_diff;

fn golden() -> Vec<u8> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fixtures/golden/golden.safetensors");
    std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

fn f32s(st: &SafeTensors, key: &str) -> Vec<f32> {
    values(st, key, safetensors::Dtype::F32, f32::from_le_bytes)
}

fn i64s(st: &SafeTensors, key: &str) -> Vec<i64> {
    values(st, key, safetensors::Dtype::I64, i64::from_le_bytes)
}

/// The values of `key`, which must be of `dtype`, each read from its `N` little-endian bytes.
fn values<T, const N: usize>(
    st: &SafeTensors,
    key: &str,
    dtype: safetensors::Dtype,
    from_le: fn([u8; N]) -> T,
) -> Vec<T> {
    let t = st.tensor(key).unwrap();
    assert_eq!(t.dtype(), dtype, "{key}");
    t.data()
        .chunks_exact(N)
        .map(|c| from_le(c.try_into().unwrap()))
        .collect()
}

#[test]
fn golden_rays_from_c2w_and_pixels() {
    let bytes = golden();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let c2w = f32s(&st, "input/c2w");
    let mut m = [[0f32; 4]; 4];
    for (r, row) in m.iter_mut().enumerate() {
        row.copy_from_slice(&c2w[4 * r..4 * r + 4]);
    }
    let cam = Camera::new(1000, 1000, 1145.0, 1145.0, 500.0, 500.0, m).unwrap();
    let pixels: Vec<usize> = i64s(&st, "input/pixels")
        .chunks_exact(2)
        .map(|p| (p[1] * 1000 + p[0]) as usize)
        .collect();
    let (o, d) = cam.rays(&pixels, true);
    let o: Vec<f32> = o.into_iter().flatten().collect();
    let d: Vec<f32> = d.into_iter().flatten().collect();
    let (want_o, want_d) = (f32s(&st, "input/rays_o"), f32s(&st, "input/rays_d"));
    let (eo, ed) = (max_abs_diff(&o, &want_o), max_abs_diff(&d, &want_d));
    assert!(eo < 1e-6, "rays_o max diff {eo}");
    assert!(ed < 1e-6, "rays_d max diff {ed}");
    // A half-pixel shift (a common convention the reference does not use) is far off.
    let shifted: Vec<f32> = pixels
        .iter()
        .flat_map(|&p| {
            let (x, y) = ((p % 1000) as f32 + 0.5, (p / 1000) as f32 + 0.5);
            let dc = [(x - 500.0) / 1145.0, -(y - 500.0) / 1145.0, -1.0];
            let v: Vec<f32> = (0..3)
                .map(|r| (0..3).map(|k| m[r][k] * dc[k]).sum())
                .collect();
            let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            v.into_iter().map(move |x| x / n)
        })
        .collect();
    assert!(max_abs_diff(&shifted, &want_d) > 1e-5);
}

#[test]
fn golden_cylinder_from_kp3d() {
    let bytes = golden();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let kp = f32s(&st, "input/kp3d");
    let cyls = f32s(&st, "input/cyls");
    let mut joints: Joints = [[0.0; 3]; N_JOINTS];
    for (j, r) in joints.iter_mut().enumerate() {
        r.copy_from_slice(&kp[3 * j..3 * j + 3]);
    }
    let got = cylinder_from_joints(&joints, &CylinderParams::training(HeadDir::NegY));
    let e = max_abs_diff(&got, &cyls[..5]);
    assert!(e < 1e-5, "cyls max diff {e}: {got:?} vs {:?}", &cyls[..5]);
    // Head +y would put the caps on the other side.
    let flipped = cylinder_from_joints(&joints, &CylinderParams::training(HeadDir::PosY));
    assert!(max_abs_diff(&flipped, &cyls[..5]) > 0.1);
}
