//! Named intermediates of a forward pass, for the parity tests against the reference and
//! for debugging. Keys follow the golden manifest (`coarse/gnn_feat`, `fine/w_p`, ...).

use std::collections::BTreeMap;

use candle_core::Tensor;

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
}
