//! The radiance field heads (paper Eq. 9 and the NeRF heads): the density trunk on the
//! modulator output S, the density and colour heads, and the per-image frame codes.

use candle_core::{Tensor, D};

use crate::compute::numerics::Numerics;
use crate::error::{ModelError, Result};
use crate::network::config::Config;
use crate::network::nn::Linear;
use crate::network::params::{Init, Params};

/// Intermediates of one field evaluation (for parity tests).
#[derive(Debug, Clone)]
pub struct FieldOutputs {
    /// density_l0_pre_relu: [N,W] (when asked for: a fused linear-ReLU keeps no input)
    pub l0_pre: Option<Tensor>,
    /// density feature h: [N,W] (after the last ReLU)
    pub feature: Tensor,
    /// sigma_raw: [N,1] before noise and ReLU
    pub sigma_raw: Tensor,
    /// feature_linear(h): [N,W]
    pub feature_linear: Tensor,
    /// views_linears.0 before ReLU: [N,view_W] (when asked for)
    pub view_pre: Option<Tensor>,
    /// rgb logits: [N,3]
    pub rgb_logits: Tensor,
    /// rgb = 1.002·sigmoid(logits) − 0.001: [N,3]
    pub rgb: Tensor,
}

#[derive(Debug, Clone)]
pub struct Field {
    pts_linears: Vec<Linear>,
    skips: Vec<usize>,
    sigma: Linear,
    feature: Linear,
    view: Linear,
    rgb: Linear,
}

impl Field {
    /// `pts_linears.*`, `sigma_linear`, `views_linears.0`, `feature_linear`, `rgb_linear`
    /// (in that order, the reference's), all with torch's default init.
    pub fn new<'a>(p: impl Into<Params<'a>>, cfg: &Config) -> Result<Self> {
        let p = p.into();
        let w = cfg.trunk_width;
        let s_dim = cfg.trunk_input_dim();
        let linear = |name: &str, fan_in: usize, out: usize| {
            Linear::new(p.pp(name), fan_in, out, Init::torch_default(fan_in))
        };
        let mut pts_linears = Vec::new();
        for i in 0..cfg.trunk_depth {
            let fan_in = if i == 0 {
                s_dim
            } else if cfg.skips.contains(&(i - 1)) {
                w + s_dim
            } else {
                w
            };
            pts_linears.push(linear(&format!("pts_linears.{i}"), fan_in, w)?);
        }
        let code = if cfg.use_framecodes {
            cfg.framecode_ch
        } else {
            0
        };
        let sigma = linear("sigma_linear", w, 1)?;
        let view_in = w + cfg.sh_degree * cfg.sh_degree + code;
        let view = linear("views_linears.0", view_in, cfg.view_width)?;
        let feature = linear("feature_linear", w, w)?;
        let rgb = linear("rgb_linear", cfg.view_width, 3)?;
        Ok(Self {
            pts_linears,
            skips: cfg.skips.clone(),
            sigma,
            feature,
            view,
            rgb,
        })
    }

    /// s: [N,K·F] modulator output; view: [N,SH+code] view features -> outputs; the
    /// pre-ReLU values `l0_pre` and `view_pre` when `keep_pre` (traces).
    pub fn forward(
        &self,
        s: &Tensor,
        view: &Tensor,
        k: Numerics,
        keep_pre: bool,
    ) -> Result<FieldOutputs> {
        let (h, l0_pre) = self.trunk(s, k, keep_pre)?;
        let sigma_raw = self.sigma.forward(&h, k)?;
        let feature_linear = self.feature.forward(&h, k)?;
        let (view_pre, rgb_logits, rgb) = self.colour(&feature_linear, view, k, keep_pre)?;
        Ok(FieldOutputs {
            l0_pre,
            feature: h,
            sigma_raw,
            feature_linear,
            view_pre,
            rgb_logits,
            rgb,
        })
    }

    /// The heads of M points seen along R rays: s: [M,K·F], view: [R,SH+code], rows: [R]
    /// (u32, the point of each ray). The trunk, the density and the feature layer run once
    /// per point; the colour layers once per ray. Returns (rgb [R,3], sigma_raw [R,1]), row
    /// for row what [`Self::forward`] gives for the points repeated once per ray.
    pub fn forward_gathered(
        &self,
        s: &Tensor,
        view: &Tensor,
        rows: &Tensor,
        k: Numerics,
    ) -> Result<(Tensor, Tensor)> {
        let (h, _) = self.trunk(s, k, false)?;
        let sigma_raw =
            crate::compute::ops::rows::select_rows(&self.sigma.forward(&h, k)?, rows, k)?;
        let feature_linear =
            crate::compute::ops::rows::select_rows(&self.feature.forward(&h, k)?, rows, k)?;
        let (_, _, rgb) = self.colour(&feature_linear, view, k, false)?;
        Ok((rgb, sigma_raw))
    }

    /// The density head alone on s: [N,K·F] -> sigma_raw [N,1], as [`Self::forward`]
    /// computes it.
    pub fn density(&self, s: &Tensor, k: Numerics) -> Result<Tensor> {
        let (h, _) = self.trunk(s, k, false)?;
        self.sigma.forward(&h, k)
    }

    /// Each ReLU layer is one op with its linear layer unless a pre-ReLU value is wanted
    /// or the trunk emulates bf16.
    fn linear_relu(
        layer: &Linear,
        h: &Tensor,
        k: Numerics,
        keep: bool,
    ) -> Result<(Tensor, Option<Tensor>)> {
        if !keep && !k.bf16_trunk {
            return Ok((layer.forward_relu(h, k)?, None));
        }
        let pre = match k.bf16_trunk {
            true => layer.forward_bf16(h, k)?,
            false => layer.forward(h, k)?,
        };
        Ok((pre.relu()?, Some(pre)))
    }

    /// The density trunk on s -> (h after the last ReLU, the first layer's pre-ReLU value
    /// when `keep_l0`).
    fn trunk(&self, s: &Tensor, k: Numerics, keep_l0: bool) -> Result<(Tensor, Option<Tensor>)> {
        let mut h = s.clone();
        let mut l0_pre = None;
        for (i, layer) in self.pts_linears.iter().enumerate() {
            let (out, pre) = Self::linear_relu(layer, &h, k, keep_l0 && i == 0)?;
            if i == 0 {
                l0_pre = pre;
            }
            h = out;
            if self.skips.contains(&i) {
                // The reference concatenates the input first, then the features.
                h = Tensor::cat(&[s, &h], D::Minus1)?;
            }
        }
        Ok((h, l0_pre))
    }

    /// The colour head on feature_linear(h) and the view features -> (view layer pre-ReLU
    /// when `keep_pre`, rgb logits, rgb = 1.002·sigmoid(logits) − 0.001).
    fn colour(
        &self,
        feature_linear: &Tensor,
        view: &Tensor,
        k: Numerics,
        keep_pre: bool,
    ) -> Result<(Option<Tensor>, Tensor, Tensor)> {
        let view_in = Tensor::cat(&[feature_linear, view], D::Minus1)?;
        let (view_h, view_pre) = Self::linear_relu(&self.view, &view_in, k, keep_pre)?;
        let rgb_logits = self.rgb.forward(&view_h, k)?;
        let rgb = candle_nn::ops::sigmoid(&rgb_logits)?.affine(1.002, -0.001)?;
        Ok((view_pre, rgb_logits, rgb))
    }
}

/// Per-training-image latent codes (`framecodes.codes.weight` [n,ch]).
#[derive(Debug, Clone)]
pub struct FrameCodes {
    pub weight: Tensor,
    fix_clamp: bool,
}

impl FrameCodes {
    /// `framecodes.codes.weight` [n,ch], Xavier-normal.
    pub fn new<'a>(p: impl Into<Params<'a>>, cfg: &Config) -> Result<Self> {
        let (n, ch) = (cfg.n_framecodes, cfg.framecode_ch);
        let std = (2.0 / (n + ch) as f64).sqrt();
        Ok(Self {
            weight: p.into().param([n, ch], "codes.weight", Init::Normal(std))?,
            fix_clamp: cfg.quirks.fix_framecode_clamp,
        })
    }

    /// Codes for indices idx: [R] -> [R,ch].
    ///
    /// Outside training, a call whose indices are all negative gets the mean of all codes
    /// (unseen frames). Indices beyond the table are clamped to the last code when the
    /// largest exceeds n (the reference's rule, which lets `idx == n` through and crashes:
    /// here that is an error unless `quirks.fix_framecode_clamp`).
    pub fn lookup(&self, idx: &[i64], training: bool, k: Numerics) -> Result<Tensor> {
        let n = self.weight.dim(0)? as i64;
        let r = idx.len();
        if !training && !idx.is_empty() && idx.iter().all(|&i| i < 0) {
            return Ok(self
                .weight
                .mean_keepdim(0)?
                .broadcast_as((r, self.weight.dim(1)?))?
                .contiguous()?);
        }
        if let Some(&bad) = idx.iter().find(|&&i| i < 0) {
            return Err(ModelError::Input(format!(
                "frame-code index {bad} is negative while others are not (use -1 for every ray to get the mean code)"
            )));
        }
        let max = idx.iter().copied().max().unwrap_or(0);
        let clamp = if self.fix_clamp { max >= n } else { max > n };
        if !clamp && max >= n {
            return Err(ModelError::Input(format!(
                "frame-code index {max} is out of range for {n} codes (the reference crashes here; \
                 set quirks.fix_framecode_clamp to clamp it)"
            )));
        }
        let ids: Vec<u32> = idx
            .iter()
            .map(|&i| if clamp { i.min(n - 1) as u32 } else { i as u32 })
            .collect();
        let ids = Tensor::from_vec(ids, r, self.weight.device())?;
        // A row gather whose gradient is parallel on CUDA (bit-identical on the CPU).
        crate::compute::ops::rows::select_rows(&self.weight, &ids, k)
    }
}
