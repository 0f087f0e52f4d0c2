//! The Adam kernel against candle's ops ([`crate::compute::kernel::check`]).

use candle_core::{DType, Device, Tensor};

use super::{slot_index, update, Update, MODULE};
use crate::compute::kernel::check::{cases, random, relative_error, Case, Size, TOL};
use crate::compute::kernel::launch::with_block_limit;

/// One update's tensors, taken with torch's default betas and eps.
pub(super) struct Inputs {
    pub g: Tensor,
    pub params: Vec<Tensor>,
    pub m: Tensor,
    pub v: Tensor,
    pub slot_of: Tensor,
    pub step_size: Tensor,
    pub bias2_sqrt: Tensor,
}

impl Inputs {
    /// The update of these tensors where `has` has a gradient, with the skip flag `apply`
    /// and the clip factor `coef`.
    pub(super) fn update<'a>(
        &'a self,
        has: &'a [bool],
        apply: Option<&'a Tensor>,
        coef: Option<&'a Tensor>,
    ) -> Update<'a> {
        Update {
            g: &self.g,
            params: &self.params,
            m: &self.m,
            v: &self.v,
            slot_of: &self.slot_of,
            has,
            apply,
            coef,
            step_size: &self.step_size,
            bias2_sqrt: &self.bias2_sqrt,
            b1: 0.9,
            b2: 0.999,
            eps: 1e-8,
        }
    }
}

/// Updates of slots of awkward sizes: all with gradients, one without and a clip factor,
/// the skip flag off; in the full check also a grid of 2 blocks and a million elements.
pub(super) fn check(device: &Device, size: Size) -> crate::error::Result<Vec<Case>> {
    let all: [(&[usize], u32); 3] = [
        (&[7, 300, 1], 0),
        (&[1_000_003, 2_049], 0),
        (&[513, 3, 257, 64], 2),
    ];
    let mut out = Vec::new();
    for &(slots, blocks) in cases(size, &all) {
        let n: usize = slots.iter().sum();
        let s = slots.len();
        let seed = n as u64;
        let inputs = Inputs {
            params: slots
                .iter()
                .enumerate()
                .map(|(i, &len)| random(&[len], seed + i as u64, (-1.0, 1.0), device))
                .collect::<crate::error::Result<_>>()?,
            g: random(&[n], seed + 100, (-2.0, 2.0), device)?,
            m: random(&[n], seed + 101, (-0.1, 0.1), device)?,
            v: random(&[n], seed + 102, (0.0, 0.01), device)?,
            slot_of: slot_index(slots, device)?,
            step_size: random(&[s], seed + 103, (1e-4, 1e-3), device)?.to_dtype(DType::F64)?,
            bias2_sqrt: random(&[s], seed + 104, (0.05, 1.0), device)?.to_dtype(DType::F64)?,
        };
        let coef = Tensor::new(0.37f32, device)?;
        let (on, off) = (Tensor::new(1u8, device)?, Tensor::new(0u8, device)?);
        let mut without = vec![true; s];
        without[s / 2] = false;
        let all = vec![true; s];
        type Variant<'a> = (&'a str, &'a [bool], Option<&'a Tensor>, Option<&'a Tensor>);
        let variants: [Variant; 3] = [
            ("all slots", &all, None, None),
            (
                "a slot without gradient, clipped",
                &without,
                Some(&on),
                Some(&coef),
            ),
            ("skipped", &all, Some(&off), None),
        ];
        for (what, has, apply, coef) in variants {
            let u = inputs.update(has, apply, coef);
            let run = || update(&u);
            let kernel = if blocks > 0 {
                with_block_limit(blocks, run)?
            } else {
                run()?
            };
            let generic = crate::compute::kernel::health::generic_for(&MODULE, run)?;
            let label = format!(
                "{n} elements in {s} slots, {what}{}",
                if blocks > 0 {
                    format!(", {blocks} blocks")
                } else {
                    String::new()
                }
            );
            for (name, a, b) in [
                ("p", &kernel.0, &generic.0),
                ("m", &kernel.1, &generic.1),
                ("v", &kernel.2, &generic.2),
            ] {
                out.push(Case {
                    what: format!("{label} {name}"),
                    max_err: relative_error(a, b)?,
                    tol: TOL,
                });
            }
        }
    }
    Ok(out)
}
