//! The cost model of step accounting: counts to an estimated time on a named GPU (vendor
//! datasheet figures, an assumed launch overhead and sync latency). Every time it gives is an
//! estimate.

use serde::{Deserialize, Serialize};

use super::{Cost, Counts};

/// Datasheet figures of a GPU and the host link, for [`estimate`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Gpu {
    pub name: &'static str,
    /// Memory bandwidth, bytes/s.
    pub mem_bandwidth: f64,
    /// FP32 peak without tensor cores, FLOP/s.
    pub fp32_flops: f64,
    /// TF32 tensor-core peak (dense), FLOP/s.
    pub tf32_flops: f64,
    /// Host link, one direction, bytes/s.
    pub host_link: f64,
    pub source: &'static str,
}

/// Host time of one kernel launch (or memcpy/memset call) on the stream: an assumed figure
/// of the usual order for CUDA launches from a host API (a few µs), not a measurement.
pub const LAUNCH_S: f64 = 5e-6;
/// Latency of one device → host read: the stream drains, a small copy, the host wakes. An
/// assumed figure, not a measurement.
pub const SYNC_S: f64 = 20e-6;

/// The GPUs [`estimate`] knows.
pub const GPUS: [Gpu; 3] = [
    Gpu {
        name: "H200",
        mem_bandwidth: 4.8e12,
        fp32_flops: 67e12,
        tf32_flops: 494.5e12,
        host_link: 64e9,
        source: "NVIDIA H200 Tensor Core GPU datasheet (SXM): 4.8 TB/s HBM3e, FP32 67 TFLOPS, \
                 TF32 Tensor Core 989 TFLOPS with sparsity (494.5 dense), PCIe Gen5 128 GB/s \
                 (64 GB/s each way)",
    },
    Gpu {
        name: "H100-SXM",
        mem_bandwidth: 3.35e12,
        fp32_flops: 67e12,
        tf32_flops: 494.5e12,
        host_link: 64e9,
        source: "NVIDIA H100 Tensor Core GPU datasheet (SXM): 3.35 TB/s HBM3, FP32 67 TFLOPS, \
                 TF32 Tensor Core 989 TFLOPS with sparsity (494.5 dense), PCIe Gen5 128 GB/s \
                 (64 GB/s each way)",
    },
    Gpu {
        name: "RTX-3090",
        mem_bandwidth: 936e9,
        fp32_flops: 35.6e12,
        tf32_flops: 35.6e12,
        host_link: 32e9,
        source: "NVIDIA Ampere GA102 GPU architecture whitepaper (GeForce RTX 3090): 936 GB/s \
                 GDDR6X, peak FP32 35.6 TFLOPS, peak TF32 Tensor 35.6 TFLOPS dense (71 with \
                 sparsity), PCIe Gen4 x16 (32 GB/s each way)",
    },
];

/// [`GPUS`] by name (case-insensitive).
pub fn gpu(name: &str) -> Option<&'static Gpu> {
    GPUS.iter().find(|g| g.name.eq_ignore_ascii_case(name))
}

/// An estimated time (seconds) and its parts. Every field is an estimate.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub est_s: f64,
    /// Σ over ops of max(bytes / bandwidth, FLOPs / peak).
    pub est_roofline_s: f64,
    /// Launches and uploads × [`LAUNCH_S`].
    pub est_launch_s: f64,
    /// Syncs × [`SYNC_S`].
    pub est_sync_s: f64,
    /// Uploaded and read-back bytes over the host link.
    pub est_transfer_s: f64,
}

/// Roofline plus launch cost: per op max(bytes / bandwidth, FLOPs / peak) + launches ×
/// [`LAUNCH_S`]; per upload (explicit or of dims/strides) another [`LAUNCH_S`]; per sync
/// [`SYNC_S`]; transferred bytes over the host link. Matmuls run at the FP32 peak, or the
/// TF32 tensor-core peak with `tf32`. Additive: it ignores that launches overlap running
/// kernels, so where kernels are long it overstates, and it assumes every kernel reaches
/// the roofline, so where they are short and serial it understates.
pub fn estimate<'a>(
    costs: impl IntoIterator<Item = &'a Cost>,
    counts: &Counts,
    gpu: &Gpu,
    tf32: bool,
) -> Estimate {
    let peak = if tf32 { gpu.tf32_flops } else { gpu.fp32_flops };
    let (mut roof, mut launches) = (0.0, counts.all_uploads() as f64);
    for c in costs {
        roof += (c.bytes as f64 / gpu.mem_bandwidth).max(c.flops as f64 / peak);
        launches += f64::from(c.launches);
    }
    let e = Estimate {
        est_roofline_s: roof,
        est_launch_s: launches * LAUNCH_S,
        est_sync_s: counts.syncs as f64 * SYNC_S,
        est_transfer_s: (counts.upload_bytes + counts.sync_bytes) as f64 / gpu.host_link,
        est_s: 0.0,
    };
    Estimate {
        est_s: e.est_roofline_s + e.est_launch_s + e.est_sync_s + e.est_transfer_s,
        ..e
    }
}

/// A run's estimated time on one GPU, with FP32 matmuls and with TF32 tensor-core matmuls.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GpuEstimate {
    pub gpu: &'static str,
    pub est_fp32_matmul: Estimate,
    pub est_tf32_matmul: Estimate,
}

/// [`estimate`] on every GPU of [`GPUS`].
pub fn estimates<'a>(
    costs: impl Iterator<Item = &'a Cost> + Clone,
    counts: &Counts,
) -> Vec<GpuEstimate> {
    GPUS.iter()
        .map(|g| GpuEstimate {
            gpu: g.name,
            est_fp32_matmul: estimate(costs.clone(), counts, g, false),
            est_tf32_matmul: estimate(costs.clone(), counts, g, true),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn estimate_is_roofline_plus_launches_and_syncs() {
        let gpu = gpu("h100-sxm").unwrap();
        let costs = [
            // memory-bound: 3.35 GB at 3.35 TB/s = 1 ms
            Cost {
                op: "a",
                launches: 1,
                bytes: 3_350_000_000,
                flops: 0,
            },
            // compute-bound: 67 GFLOP at 67 TFLOP/s = 1 ms (TF32: 67/494.5 ms)
            Cost {
                op: "b",
                launches: 2,
                bytes: 8,
                flops: 67_000_000_000,
            },
        ];
        let counts = Counts {
            syncs: 2,
            param_uploads: 1,
            ..Default::default()
        };
        let e = estimate(&costs, &counts, gpu, false);
        assert!((e.est_roofline_s - 2e-3).abs() < 1e-12);
        assert!((e.est_launch_s - 4.0 * LAUNCH_S).abs() < 1e-15);
        assert!((e.est_sync_s - 2.0 * SYNC_S).abs() < 1e-15);
        let t = estimate(&costs, &counts, gpu, true);
        assert!((t.est_roofline_s - (1e-3 + 67e9 / 494.5e12)).abs() < 1e-12);
        assert!((e.est_s - (2e-3 + 4.0 * LAUNCH_S + 2.0 * SYNC_S)).abs() < 1e-12);
    }
}
