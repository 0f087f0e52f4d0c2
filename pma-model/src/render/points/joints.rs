//! Network calls grouped by the joints their samples need (`cull_joints`): a sort key that
//! lays samples out limb by limb, the calls over sorted samples, and the joints each carries.

use pma_data::skeleton::N_JOINTS;

use crate::render::cull::JointMask;

/// SMPL's joints limb by limb (left leg, right leg, spine, neck and head, left arm, right
/// arm), each from the body outwards: samples sorted by their joints in this order lie limb
/// by limb, so that consecutive samples need neighbouring joints.
const CHAIN: [u32; N_JOINTS] = [
    1, 4, 7, 10, 2, 5, 8, 11, 0, 3, 6, 9, 12, 15, 13, 16, 18, 20, 22, 14, 17, 19, 21, 23,
];

/// A joint mask with its bits moved to their joints' places in [`CHAIN`] (the sort key of
/// the joint grouping).
pub(crate) fn chain_key(mask: JointMask) -> u32 {
    CHAIN
        .iter()
        .enumerate()
        .filter(|&(_, &j)| mask >> j & 1 == 1)
        .fold(0, |key, (place, _)| key | 1 << place)
}

/// The calls over samples sorted by [`chain_key`] with joint masks `masks`: (start, len,
/// union of their masks). A call takes at most `chunk` samples and, once it holds
/// [`MIN_JOINT_CALL`], no sample that would make it carry more than [`MAX_CALL_JOINTS`]
/// joints: much smaller calls pay the per-op overhead of the ~170 ops a call runs.
pub(crate) fn joint_calls(masks: &[JointMask], chunk: usize) -> Vec<(usize, usize, JointMask)> {
    let mut calls = Vec::new();
    let (mut start, mut union): (usize, JointMask) = (0, 0);
    for (i, &m) in masks.iter().enumerate() {
        let len = i - start;
        let grown = union | m;
        if len == chunk || (len >= MIN_JOINT_CALL && grown.count_ones() > MAX_CALL_JOINTS) {
            calls.push((start, len, union));
            (start, union) = (i, m);
        } else {
            union = grown;
        }
    }
    calls.push((start, masks.len() - start, union));
    calls
}

/// The joints a call with union mask `union` carries: `None` (all 24) for a full or an
/// empty mask.
pub(crate) fn call_joints(union: JointMask) -> Option<Vec<u32>> {
    let count = union.count_ones() as usize;
    (count > 0 && count < N_JOINTS).then(|| {
        (0..N_JOINTS as u32)
            .filter(|j| union >> j & 1 == 1)
            .collect()
    })
}

/// Fewest samples of a call that may be closed early to keep its joints few. A `cpu-small`
/// point costs no more in a call of 256 than of 4,096 (example `joint_cost --points`; 64
/// costs ~1.3× more), and the smaller floor lets calls carry fewer joints: 256 with
/// [`MAX_CALL_JOINTS`] 4 rendered ~1.2× faster on one worker than 1,024 with 8.
const MIN_JOINT_CALL: usize = 256;
/// Joints a call should not exceed (once it holds [`MIN_JOINT_CALL`] samples).
const MAX_CALL_JOINTS: u32 = 4;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::cull::ALL_JOINTS;

    #[test]
    fn joint_calls_cover_the_samples_and_keep_their_joints_few() {
        // Masks as sorted samples come: runs of neighbouring joints.
        let masks: Vec<u32> = (0..5000u32).map(|i| 0b11 << (i / 400).min(22)).collect();
        for chunk in [4096, 1500, 700] {
            let calls = joint_calls(&masks, chunk);
            let mut next = 0;
            for &(start, len, union) in &calls {
                assert_eq!(start, next, "calls are contiguous");
                assert!(
                    len > 0 && len <= chunk,
                    "call of {len} samples (chunk {chunk})"
                );
                let want = masks[start..start + len].iter().fold(0, |a, b| a | b);
                assert_eq!(union, want, "union of the call's masks");
                // A call is only closed for its joints once it is big enough.
                if start + len < masks.len() && len < chunk {
                    assert!(len >= MIN_JOINT_CALL);
                    assert!((union | masks[start + len]).count_ones() > MAX_CALL_JOINTS);
                }
                next = start + len;
            }
            assert_eq!(next, masks.len(), "every sample is in a call");
            if chunk >= MIN_JOINT_CALL {
                let widest = calls.iter().map(|c| c.2.count_ones()).max().unwrap();
                assert!(widest <= MAX_CALL_JOINTS, "a call carries {widest} joints");
            }
        }
        // chain_key keeps a mask's joints (one bit per joint) and orders limb by limb.
        assert_eq!(chain_key(ALL_JOINTS), ALL_JOINTS);
        assert!(
            chain_key(1 << 1) < chain_key(1 << 2),
            "left leg before right leg"
        );
        assert!(
            chain_key(1 << 10) < chain_key(1 << 0),
            "legs before the spine"
        );
        assert!(
            chain_key(1 << 22) < chain_key(1 << 14),
            "left arm before right arm"
        );
    }
}
