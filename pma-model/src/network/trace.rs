//! Named intermediates of a forward pass, for the parity tests against the reference and
//! for debugging. Keys follow the golden manifest (`coarse/gnn_feat`, `fine/w_p`, ...).

use std::collections::BTreeMap;

use candle_core::Tensor;

use crate::error::Result;

#[derive(Debug, Default, Clone)]
pub struct Trace {
    pub tensors: BTreeMap<String, Tensor>,
}

impl Trace {
    pub fn put(&mut self, key: impl Into<String>, t: &Tensor) {
        self.tensors.insert(key.into(), t.clone());
    }

    /// Record `items` under `stage/name`.
    pub fn put_stage(&mut self, stage: &str, items: &[(&str, &Tensor)]) {
        for (name, t) in items {
            self.put(format!("{stage}/{name}"), t);
        }
    }

    /// Join per-pose traces in ray order (poses are contiguous ray blocks): the modulation
    /// tensors are stacked per layer, so they join along dim 1, everything else along dim 0.
    pub fn concat_poses(&mut self, parts: &[Trace]) -> Result<()> {
        let Some(first) = parts.first() else {
            return Ok(());
        };
        for key in first.tensors.keys() {
            let ts: Vec<Tensor> = parts.iter().map(|t| t.tensors[key].clone()).collect();
            let dim = if key.ends_with("mod_freq") || key.ends_with("mod_phase") {
                1
            } else {
                0
            };
            self.put(key.clone(), &Tensor::cat(&ts, dim)?);
        }
        Ok(())
    }
}
