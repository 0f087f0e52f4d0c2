//! The two-stage window (paper Eqs. 4–6): the spatial window w^p from the
//! bone-normalised point x̄, and the learned feature window w^f from a max-pool over the
//! joints' part features. Their product w selects which parts describe a point.

use candle_core::{Tensor, D};

use crate::compute::numerics::Numerics;
use crate::error::Result;
use crate::network::config::Config;
use crate::network::nn::{Linear, SineLayer};
use crate::network::params::{Init, Params};

/// Spatial window `w^p = exp(−α Σ_k x̄_k^β)`: x_bar: [N,J,3] -> [N,J], detached as in the
/// reference (it does not train the box sizes). The power is computed by repeated squaring
/// (never exp/log), so negative components and huge |x̄| stay exact or underflow to 0.
pub fn spatial_window(x_bar: &Tensor, alpha: f64, beta: u32) -> Result<Tensor> {
    let x = x_bar.detach();
    let sq = x.sqr()?;
    let mut p = sq.clone();
    for _ in 1..beta / 2 {
        p = (p * &sq)?;
    }
    Ok((p.sum(D::Minus1)? * -alpha)?.exp()?)
}

/// Outputs of the window for one pose group of points.
#[derive(Debug, Clone)]
pub struct Window {
    /// w: [N,J] = w^p · w^f
    pub w: Tensor,
    /// w_f: [N,J] feature window
    pub w_f: Tensor,
    /// logits: [N,J] before the sigmoid
    pub logits: Tensor,
    /// pooled: [N,H] max over joints of the attenuated part features
    pub pooled: Tensor,
}

/// `WinFun`: part features `f^p_j = layer_pose(G_j) + layer_point(e_j)`, attenuated by
/// w^p, max-pooled over joints, then two sine layers, a linear layer and a sigmoid.
#[derive(Debug, Clone)]
pub struct WinFun {
    layer_pose: Linear,
    /// The learned feature window; absent in variants that do not use w^f.
    feature: Option<FeatureWindow>,
}

#[derive(Debug, Clone)]
struct FeatureWindow {
    layer_point: Linear,
    sin0: SineLayer,
    sin1: SineLayer,
    last: Linear,
}

impl WinFun {
    /// `win_fun.*`; every weight, the linear ones included, has SIREN's init.
    pub fn new<'a>(p: impl Into<Params<'a>>, cfg: &Config) -> Result<Self> {
        let p = p.into();
        let (h, w0) = (cfg.win_hidden, cfg.sin_w0_pose);
        let (gw, ce) = (cfg.gnn_width, cfg.point_enc_dim);
        let layer_pose = Linear::new(p.pp("layer_pose.layer"), gw, h, Init::siren(gw, w0))?;
        let feature = match cfg.variant.feature_window() {
            true => Some(FeatureWindow {
                layer_point: Linear::new(p.pp("layer_point.layer"), ce, h, Init::siren(ce, w0))?,
                sin0: SineLayer::new(p.pp("sin_lin0"), h, h, w0, Init::siren(h, w0))?,
                sin1: SineLayer::new(p.pp("sin_lin1"), h, h, w0, Init::siren(h, w0))?,
                last: Linear::new(
                    p.pp("last_layer.layer"),
                    h,
                    cfg.n_joints,
                    Init::siren(h, w0),
                )?,
            }),
            false => None,
        };
        Ok(Self {
            layer_pose,
            feature,
        })
    }

    /// Per-pose projection g = layer_pose(G): [P,J,C] -> [P,J,H]. Computed once per pose;
    /// it also is the feature that f^m aggregates.
    pub fn project_pose(&self, g_feat: &Tensor, k: Numerics) -> Result<Tensor> {
        self.layer_pose.forward(g_feat, k)
    }

    /// The points of P poses: g: [P,J,H] (each pose's projection), e: [N,J,Ce] pose-branch
    /// point encodings, w_p: [N,J] spatial window, with the N points grouped by pose in P
    /// equal blocks. `joints`: the joints the J rows are (a subset of all, the others having
    /// w^p = 0 at every point), or `None` for all.
    pub fn forward(
        &self,
        g: &Tensor,
        e: &Tensor,
        w_p: &Tensor,
        joints: Option<&Tensor>,
        k: Numerics,
    ) -> Result<Window> {
        // layer_point's bias is added to the per-pose g ([P,J,H]) rather than to every point:
        // one pass over the [N,J,H] part features fewer, forward and backward (the bias
        // gradient is then a sum over P·J rows, not over N·J).
        let f = self.feature.as_ref().ok_or_else(|| {
            crate::error::ModelError::Config("this variant has no feature window".into())
        })?;
        let (n, j, ce) = e.dims3()?;
        let g_b = g.broadcast_add(&f.layer_point.bias)?;
        let pooled = crate::compute::ops::window_pool::window_pool_of(
            &e.reshape((n * j, ce))?,
            &f.layer_point.weight,
            &g_b,
            w_p,
            k,
        )?;
        // A left-out joint's attenuated feature is 0 (w^p = 0): its entry of the max.
        let pooled = match joints {
            Some(_) => pooled.relu()?,
            None => pooled,
        };
        let h = f.sin1.forward(&f.sin0.forward(&pooled, k)?, k)?;
        let logits = f.last.forward(&h, k)?;
        let w_f = candle_nn::ops::sigmoid(&logits)?;
        let w_f = match joints {
            Some(js) => w_f.index_select(js, 1)?,
            None => w_f,
        };
        let w = (w_p * &w_f)?;
        Ok(Window {
            w,
            w_f,
            logits,
            pooled,
        })
    }
}

/// Aggregated pose feature `f^m = Σ_j w_j g_j` (a plain sum, not normalised):
/// w: [N,J], g: [P,J,H] -> [N,H], the N points grouped by pose in P equal blocks (one
/// batched product).
pub fn aggregate(w: &Tensor, g: &Tensor) -> Result<Tensor> {
    let (n, j) = w.dims2()?;
    let (p, _, h) = g.dims3()?;
    if p == 0 || n % p != 0 {
        return Err(crate::error::ModelError::Input(format!(
            "f^m: {n} points cannot be split into {p} equal per-pose blocks"
        )));
    }
    Ok(w.reshape((p, n / p, j))?.matmul(g)?.reshape((n, h))?)
}
