//! Pose-dependent frequency modulation (paper Eqs. 7–8): the `PoseExtractor`
//! predicts per-layer frequencies Θ and phases Φ from the aggregated pose feature f^m,
//! and the FiLM-SIREN `Modulator` runs the windowed point encoding through sine layers
//! whose frequencies and phases are those predictions.

use candle_core::Tensor;
use pma_data::skeleton::N_JOINTS;

use crate::compute::numerics::Numerics;
use crate::error::Result;
use crate::network::config::Config;
use crate::network::nn::{Linear, SineLayer};
use crate::network::params::{Init, Params};

/// Frequencies Θ and phases Φ of the modulated layers, one [N,F] tensor per layer.
#[derive(Debug, Clone)]
pub struct Modulation {
    pub freq: Vec<Tensor>,
    pub phase: Vec<Tensor>,
    /// The pose extractor's whole head output [N,2·K·F] that `freq` and `phase` are views
    /// of, when they are. The fused FiLM-sine kernel reads both blocks from it and returns a
    /// single gradient for it, instead of two zero-padded ones per layer.
    pub head: Option<Tensor>,
}

#[derive(Debug, Clone)]
pub struct PoseExtractor {
    hidden: Vec<SineLayer>,
    head: Linear,
    n_pm: usize,
    freq_dim: usize,
}

impl PoseExtractor {
    /// `pose_extractor.*`, SIREN's init throughout (the linear head included).
    pub fn new<'a>(p: impl Into<Params<'a>>, cfg: &Config) -> Result<Self> {
        let p = p.into();
        let (h, w0) = (cfg.pose_extractor_hidden, cfg.sin_w0_pose);
        let mut hidden = Vec::new();
        for l in 0..cfg.pose_extractor_depth {
            let fan_in = if l == 0 { cfg.win_hidden } else { h };
            let init = Init::siren(fan_in, w0);
            hidden.push(SineLayer::new(
                p.pp(format!("sin_lin{l}")),
                fan_in,
                h,
                w0,
                init,
            )?);
        }
        let fan_in = if cfg.pose_extractor_depth == 0 {
            cfg.win_hidden
        } else {
            h
        };
        let head = Linear::new(
            p.pp(format!("sin_lin{}.layer", cfg.pose_extractor_depth)),
            fan_in,
            2 * cfg.n_pm * cfg.freq_dim,
            Init::siren(fan_in, w0),
        )?;
        Ok(Self {
            hidden,
            head,
            n_pm: cfg.n_pm,
            freq_dim: cfg.freq_dim,
        })
    }

    /// f_m: [N,H] -> Θ, Φ. The head's output is laid out as [Θ_0..Θ_{K-1}, Φ_0..Φ_{K-1}],
    /// each block F wide.
    pub fn forward(&self, f_m: &Tensor, k: Numerics) -> Result<Modulation> {
        let mut h = f_m.clone();
        for layer in &self.hidden {
            h = layer.forward(&h, k)?;
        }
        let o = self.head.forward(&h, k)?;
        let (n_pm, f) = (self.n_pm, self.freq_dim);
        let freq = (0..n_pm)
            .map(|i| o.narrow(1, i * f, f))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let phase = (0..n_pm)
            .map(|i| o.narrow(1, (n_pm + i) * f, f))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Modulation {
            freq,
            phase,
            head: Some(o),
        })
    }
}

#[derive(Debug, Clone)]
pub struct Modulator {
    layers: Vec<Linear>,
    w0: f64,
}

impl Modulator {
    /// `modulator.sin_lin{k}.layer.*`, SIREN's init with the point frequency ω.
    pub fn new<'a>(p: impl Into<Params<'a>>, cfg: &Config) -> Result<Self> {
        let p = p.into();
        let mut layers = Vec::new();
        for k in 0..cfg.n_pm {
            let fan_in = if k == 0 {
                cfg.n_joints * cfg.point_enc_dim
            } else {
                cfg.freq_dim
            };
            layers.push(Linear::new(
                p.pp(format!("sin_lin{k}.layer")),
                fan_in,
                cfg.freq_dim,
                Init::siren(fan_in, cfg.sin_w0_point),
            )?);
        }
        Ok(Self {
            layers,
            w0: cfg.sin_w0_point,
        })
    }

    /// Map raw predictions Θ to frequencies γ. pi-GAN's `15Θ + 30` is what the reference
    /// takes whenever ω > 15 (ω = 16 by default); otherwise `ωΘ + 2ω`.
    pub fn gamma(&self, theta: &Tensor) -> Result<Tensor> {
        let (mul, add) = self.gamma_affine();
        Ok(theta.affine(mul, add)?)
    }

    /// γ = mul·Θ + add.
    fn gamma_affine(&self) -> (f64, f64) {
        if self.w0 > 15.0 {
            (15.0, 30.0)
        } else {
            (self.w0, 2.0 * self.w0)
        }
    }

    /// The frequency of an unmodulated layer: γ at Θ = 0 (`only-syn`, with Φ = 0).
    pub fn gamma0(&self) -> f64 {
        if self.w0 > 15.0 {
            30.0
        } else {
            2.0 * self.w0
        }
    }

    /// The first layer restricted to the input columns of `joints` (each joint's block of
    /// `point_enc_dim` columns), or the layer itself for `None`.
    fn first_layer(&self, joints: Option<&Tensor>) -> Result<Linear> {
        let layer = &self.layers[0];
        let Some(js) = joints else {
            return Ok(layer.clone());
        };
        let ce = layer.weight.dim(1)? / N_JOINTS;
        let cols: Vec<u32> = js
            .to_vec1::<u32>()?
            .iter()
            .flat_map(|&j| (0..ce as u32).map(move |c| j * ce as u32 + c))
            .collect();
        let cols = Tensor::from_vec(cols, js.dim(0)? * ce, layer.weight.device())?;
        Ok(Linear {
            weight: layer.weight.index_select(&cols, 1)?,
            bias: layer.bias.clone(),
        })
    }

    /// The same layers without modulation: `h_k = sin(γ(0) (M_k h_{k-1} + ν_k))`. x_tilde
    /// holds the blocks of `joints` only when given (see [`Self::forward`]).
    pub fn forward_fixed(
        &self,
        x_tilde: &Tensor,
        joints: Option<&Tensor>,
        k: Numerics,
    ) -> Result<Tensor> {
        let first = self.first_layer(joints)?;
        let mut h = x_tilde.clone();
        let mut outs = Vec::with_capacity(self.layers.len());
        for (l, layer) in self.layers.iter().enumerate() {
            let layer = if l == 0 { &first } else { layer };
            let pre = (layer.forward(&h, k)? * self.gamma0())?;
            h = crate::compute::fast_sine::sin(&pre, k.fast_sine)?;
            outs.push(h.clone());
        }
        Ok(Tensor::cat(&outs, 1)?)
    }

    /// x_tilde: [N,J·Ce] windowed point encodings -> S: [N,K·F], the concatenated outputs
    /// `h_k = sin(γ_k ⊙ (M_k h_{k-1} + ν_k) + Φ_k)` of all modulated layers. With `joints`,
    /// x_tilde holds only those joints' blocks (the others are 0) and M_0 is taken on their
    /// columns.
    pub fn forward(
        &self,
        x_tilde: &Tensor,
        m: &Modulation,
        joints: Option<&Tensor>,
        k: Numerics,
    ) -> Result<Tensor> {
        let first = self.first_layer(joints)?;
        let layer = |l: usize| if l == 0 { &first } else { &self.layers[l] };
        if let Some(o) = &m.head {
            let n = self.layers.len();
            let head = crate::compute::ops::film_sine::FilmHead::new(o, n, self.gamma_affine(), k);
            let outs = head.stack(x_tilde, |l, h| layer(l).forward(h, k))?;
            return Ok(Tensor::cat(&outs, 1)?);
        }
        let mut h = x_tilde.clone();
        let mut outs = Vec::with_capacity(self.layers.len());
        for l in 0..self.layers.len() {
            let pre = layer(l).forward(&h, k)?;
            let arg = (pre * self.gamma(&m.freq[l])?)?.add(&m.phase[l])?;
            h = crate::compute::fast_sine::sin(&arg, k.fast_sine)?;
            outs.push(h.clone());
        }
        Ok(Tensor::cat(&outs, 1)?)
    }
}
