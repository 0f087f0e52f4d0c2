//! The pose graph network `GNN_Sine` (paper Eq. 2) and the learnable per-part box
//! half-extents ("axis scales") it owns.
//!
//! Input: the 6D rotation of every joint of every distinct pose in the batch; output: one
//! feature vector G_j per joint. All of this is per-pose work, computed once per pose.

use candle_core::Tensor;
use pma_data::skeleton::PARENTS;

use crate::error::Result;
use crate::network::config::Config;
use crate::network::nn::per_joint_matmul;
use crate::network::params::{Init, Params, RestValue};

/// Graph convolution with per-node weights: `Y_j = Σ_k (E ⊙ A)_jk (X_k W_k) + β`.
#[derive(Debug, Clone)]
struct GraphConv {
    /// lin.weight: [J,in,out]
    weight: Tensor,
    /// adj_w ⊙ adj: the learnable edge weights masked by the skeleton graph, [1,J,J].
    adj_w: Tensor,
    adj: Tensor,
    /// bias: [out] shared by all nodes.
    bias: Tensor,
}

/// Per-node linear layer: `Y_j = X_j W_j + b_j`.
#[derive(Debug, Clone)]
struct ParallelLinear {
    /// weight: [J,in,out]
    weight: Tensor,
    /// bias: [1,J,out]
    bias: Tensor,
}

#[derive(Debug, Clone)]
enum Layer {
    Graph(GraphConv),
    Node(ParallelLinear),
}

impl Layer {
    /// x: [P,J,in] -> [P,J,out] (before the sine).
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        match self {
            Layer::Graph(g) => {
                let xw = per_joint_matmul(x, &g.weight)?;
                let e = g.adj_w.mul(&g.adj)?;
                Ok(e.broadcast_matmul(&xw)?.broadcast_add(&g.bias)?)
            }
            Layer::Node(l) => Ok(per_joint_matmul(x, &l.weight)?.broadcast_add(&l.bias)?),
        }
    }
}

/// Per-layer outputs before the sine, for parity tests.
pub type GnnTrace = Vec<Tensor>;

#[derive(Debug, Clone)]
pub struct GnnSine {
    layers: Vec<Layer>,
    /// mask: [1,J,1], 0 at the root: the graph sees relative rotations only.
    mask: Tensor,
    /// axis_scale: [J,3], the learnable half-extents (raw, may go negative).
    axis_scale: Tensor,
    /// base_scale: [J,3], their initial values (the floor is a fraction of these).
    base_scale: Tensor,
    w0: f64,
    scale_floor: f64,
}

impl GnnSine {
    /// `graph_net.*` (pass `p.pp("graph_net")`), registered in the reference's order.
    pub fn new<'a>(p: impl Into<Params<'a>>, cfg: &Config) -> Result<Self> {
        let p = p.into();
        let j = cfg.n_joints;
        let gw = cfg.gnn_width;
        let axis_scale = p.param([j, 3], "axis_scale", Init::Rest(RestValue::HalfExtents))?;
        let root_mask = (0..j)
            .map(|i| if i == 0 && cfg.mask_root { 0.0 } else { 1.0 })
            .collect();
        let mask = p.buffer([1, j, 1], "mask", Init::Values(root_mask))?;
        let base_scale = p.buffer([j, 3], "base_scale", Init::Rest(RestValue::HalfExtents))?;
        let adj = adjacency(j);
        let mut layers = Vec::new();
        // Without GNN features (`only-syn`) only the box sizes above remain.
        let n_layers = match cfg.variant.gnn_features() {
            true => cfg.gnn_graph_layers + cfg.gnn_fc_layers,
            false => 0,
        };
        for l in 0..n_layers {
            let pl = p.pp(format!("layers.{l}"));
            let fan_in = if l == 0 { 6 } else { gw };
            // The reference's SIREN init reads the weight's last dim as fan-in: for the
            // [J,in,out] layout that is the fan-out (kept for parity; docs/reference.md).
            let weight_init = if l == 0 {
                Init::Uniform(1.0 / gw as f64)
            } else {
                Init::siren(gw, cfg.sin_w0_pose)
            };
            layers.push(if l < cfg.gnn_graph_layers {
                let bias = pl.param([gw], "bias", Init::Zeros)?;
                let adj_w = pl.param([1, j, j], "adj_w", Init::EdgeWeights(adj.clone()))?;
                let adj = pl.buffer([1, j, j], "adj", Init::Values(adj.clone()))?;
                Layer::Graph(GraphConv {
                    weight: pl.param([j, fan_in, gw], "lin.weight", weight_init)?,
                    adj_w,
                    adj,
                    bias,
                })
            } else {
                Layer::Node(ParallelLinear {
                    weight: pl.param([j, fan_in, gw], "weight", weight_init)?,
                    bias: pl.param([1, j, gw], "bias", Init::Zeros)?,
                })
            });
        }
        Ok(Self {
            layers,
            mask,
            axis_scale,
            base_scale,
            w0: cfg.sin_w0_pose,
            scale_floor: cfg.scale_floor,
        })
    }

    /// pose6d: [P,J,6] -> G: [P,J,C]. With `trace`, also returns every layer's pre-sine output.
    pub fn forward(&self, pose6d: &Tensor, mut trace: Option<&mut GnnTrace>) -> Result<Tensor> {
        let mut h = pose6d.broadcast_mul(&self.mask)?;
        for layer in &self.layers {
            let pre = layer.forward(&h)?;
            if let Some(t) = trace.as_deref_mut() {
                t.push(pre.clone());
            }
            h = (pre * self.w0)?.sin()?;
        }
        Ok(h)
    }

    /// Effective half-extents s: [J,3]. The value is `max(|a|, floor·b0)` but the gradient
    /// w.r.t. |a| is always 1 (the reference's straight-through floor), so the size
    /// regulariser can keep pushing the raw parameter while the value stays at the floor.
    pub fn axis_scale(&self) -> Result<Tensor> {
        // |a| written as relu(a) + relu(−a): same value, but its gradient at exactly 0 is 0
        // (torch's sign(0)), where candle's `abs` would give ±1.
        let a = (self.axis_scale.relu()? + self.axis_scale.neg()?.relu()?)?;
        let floor = (&self.base_scale * self.scale_floor)?;
        let clamped = a.maximum(&floor)?;
        Ok((&a + (clamped - &a)?.detach())?)
    }
}

/// The skeleton graph with self-loops, row-major J×J (joints beyond the SMPL 24 have no
/// edges).
fn adjacency(j: usize) -> Vec<f32> {
    let mut adj = vec![0f32; j * j];
    for i in 0..j {
        adj[i * j + i] = 1.0;
        if i > 0 && i < PARENTS.len() {
            adj[i * j + PARENTS[i]] = 1.0;
            adj[PARENTS[i] * j + i] = 1.0;
        }
    }
    adj
}
