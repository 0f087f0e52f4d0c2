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

/// NVIDIA's H200 (SXM).
const H200: Gpu = Gpu {
    name: "H200",
    mem_bandwidth: 4.8e12,
    fp32_flops: 67e12,
    tf32_flops: 494.5e12,
    host_link: 64e9,
    source: "NVIDIA H200 Tensor Core GPU datasheet (SXM): 4.8 TB/s HBM3e, FP32 67 TFLOPS, \
             TF32 Tensor Core 989 TFLOPS with sparsity (494.5 dense), PCIe Gen5 128 GB/s \
             (64 GB/s each way)",
};

/// The GPUs [`estimate`] knows.
pub const GPUS: [Gpu; 3] = [
    H200,
    // The H200's compute and host-link figures; only the memory differs.
    Gpu {
        name: "H100-SXM",
        mem_bandwidth: 3.35e12,
        source: "NVIDIA H100 Tensor Core GPU datasheet (SXM): 3.35 TB/s HBM3, FP32 67 TFLOPS, \
                 TF32 Tensor Core 989 TFLOPS with sparsity (494.5 dense), PCIe Gen5 128 GB/s \
                 (64 GB/s each way)",
        ..H200
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

/// A link between GPUs: datasheet bandwidth and the latency NCCL's own tuning model assumes
/// per step of a ring, for [`Topology::collective_s`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Link {
    pub name: &'static str,
    /// One direction, per GPU, bytes/s.
    pub bandwidth: f64,
    /// Latency of one step of a ring over this link (not a datasheet figure).
    pub step_latency_s: f64,
    pub source: &'static str,
}

/// Where the per-step latencies come from: assumed figures, not measurements.
const NCCL_TUNING: &str = "step latency: NCCL's tuning model (src/graph/tuning.cc, ring \
                           algorithm, Simple protocol), an assumed figure";

/// NVLink 4 of an H100/H200 SXM node.
pub const NVLINK4: Link = Link {
    name: "NVLink 4",
    bandwidth: 450e9,
    step_latency_s: 3.4e-6,
    source: "NVIDIA H100 and H200 Tensor Core GPU datasheets (SXM): NVLink 900 GB/s per GPU \
             (450 GB/s each way)",
};

/// PCIe Gen5 x16 between GPUs (no NVLink: a workstation's cards).
pub const PCIE5: Link = Link {
    name: "PCIe Gen5 x16",
    bandwidth: 64e9,
    step_latency_s: 5.7e-6,
    source: "NVIDIA H100 Tensor Core GPU datasheet (PCIe): PCIe Gen5 128 GB/s (64 GB/s each way)",
};

/// PCIe Gen4 x16 between GPUs (an RTX 3090 workstation).
pub const PCIE4: Link = Link {
    name: "PCIe Gen4 x16",
    bandwidth: 32e9,
    step_latency_s: 5.7e-6,
    source: "NVIDIA Ampere GA102 GPU architecture whitepaper: PCIe Gen4 x16, 64 GB/s \
             (32 GB/s each way)",
};

/// InfiniBand NDR between nodes, one 400 Gb/s port per GPU.
pub const INFINIBAND_NDR: Link = Link {
    name: "InfiniBand NDR",
    bandwidth: 50e9,
    step_latency_s: 9.6e-6,
    source: "NVIDIA ConnectX-7 datasheet: 400 Gb/s NDR InfiniBand (50 GB/s each way); NVIDIA \
             DGX H100/H200 datasheets: eight single-port ConnectX-7 (one per GPU)",
};

/// Fixed cost of one collective call besides its steps (an assumed figure, see
/// [`NCCL_TUNING`]).
pub const COLLECTIVE_BASE_S: f64 = 8.4e-6;

/// The sources of [`Link::step_latency_s`] and [`COLLECTIVE_BASE_S`].
pub const COLLECTIVE_LATENCY_SOURCE: &str = NCCL_TUNING;

/// Where the ranks of a data-parallel group run: `nodes` machines of `gpus_per_node` GPUs,
/// `intra` between the GPUs of a node, `inter` between nodes.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Topology {
    pub nodes: usize,
    pub gpus_per_node: usize,
    pub intra: &'static Link,
    pub inter: &'static Link,
}

impl Topology {
    /// `ranks` GPUs of nodes of at most `per_node` GPUs (the last node may hold fewer).
    pub fn of(ranks: usize, per_node: usize, intra: &'static Link, inter: &'static Link) -> Self {
        let per_node = per_node.max(1);
        let ranks = ranks.max(1);
        Self {
            nodes: ranks.div_ceil(per_node),
            gpus_per_node: ranks.min(per_node),
            intra,
            inter,
        }
    }

    pub fn ranks(&self) -> usize {
        self.nodes * self.gpus_per_node
    }

    /// The estimated time of the collectives in `c` as rings over this topology: a call
    /// costs [`COLLECTIVE_BASE_S`], its steps' latencies (an all-reduce 2(N − 1) steps, an
    /// all-gather N − 1; 2(nodes − 1) and nodes − 1 of them cross nodes) and the bytes each
    /// rank sends (2(N − 1)/N of its buffer for an all-reduce, N − 1 buffers for an
    /// all-gather) at the slowest link of the ring. Launches are counted with the ops. Zero
    /// for one rank.
    pub fn collective_s(&self, c: &Counts) -> f64 {
        let n = self.ranks();
        if n < 2 {
            return 0.0;
        }
        let (n, nodes) = (n as f64, self.nodes as f64);
        let slowest = if self.nodes > 1 {
            self.intra.bandwidth.min(self.inter.bandwidth)
        } else {
            self.intra.bandwidth
        };
        let steps = |total: f64, inter: f64| {
            (total - inter) * self.intra.step_latency_s + inter * self.inter.step_latency_s
        };
        let reduce = c.all_reduces as f64
            * (COLLECTIVE_BASE_S + steps(2.0 * (n - 1.0), 2.0 * (nodes - 1.0)))
            + 2.0 * (n - 1.0) / n * c.all_reduce_bytes as f64 / slowest;
        let gather = c.all_gathers as f64 * (COLLECTIVE_BASE_S + steps(n - 1.0, nodes - 1.0))
            + (n - 1.0) * c.all_gather_bytes as f64 / slowest;
        reduce + gather
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

    #[test]
    fn collectives_are_rings_over_the_slowest_link() {
        let c = Counts {
            all_reduces: 2,
            all_reduce_bytes: 8_000_000,
            all_gathers: 1,
            all_gather_bytes: 1_000,
            ..Default::default()
        };
        let one = Topology::of(1, 8, &NVLINK4, &INFINIBAND_NDR);
        assert_eq!(one.collective_s(&c), 0.0);
        // 8 GPUs of one node: 14 NVLink steps per all-reduce, 7 for the all-gather.
        let node = Topology::of(8, 8, &NVLINK4, &INFINIBAND_NDR);
        assert_eq!((node.nodes, node.gpus_per_node), (1, 8));
        let want = 2.0 * (8.4e-6 + 14.0 * 3.4e-6)
            + 2.0 * 7.0 / 8.0 * 8e6 / 450e9
            + (8.4e-6 + 7.0 * 3.4e-6)
            + 7.0 * 1e3 / 450e9;
        assert!((node.collective_s(&c) - want).abs() < 1e-12);
        // 2 × 8: the rings cross the nodes twice per all-reduce, once per all-gather, and
        // move at InfiniBand's bandwidth.
        let two = Topology::of(16, 8, &NVLINK4, &INFINIBAND_NDR);
        assert_eq!((two.nodes, two.ranks()), (2, 16));
        let want = 2.0 * (8.4e-6 + 28.0 * 3.4e-6 + 2.0 * 9.6e-6)
            + 2.0 * 15.0 / 16.0 * 8e6 / 50e9
            + (8.4e-6 + 14.0 * 3.4e-6 + 9.6e-6)
            + 15.0 * 1e3 / 50e9;
        assert!((two.collective_s(&c) - want).abs() < 1e-12);
    }
}
