//! Where a layer's tensors come from while it is built.
//!
//! Every module's constructor asks a [`Params`] for its tensors by name, shape, kind
//! (trained parameter or fixed buffer) and initialiser, the way candle-nn's `linear` passes
//! init hints to its `VarBuilder`. The same constructor then serves three purposes:
//!
//! * **loading**: the tensors come from a checkpoint (through a candle `VarBuilder`);
//! * **a fresh model**: each tensor is drawn from its initialiser, in registration order,
//!   from one seeded RNG, so a seed gives the same model on every machine;
//! * **the checkpoint layout**: only the names, shapes and kinds are recorded
//!   ([`crate::network::checkpoint::tensor_layout`]).
//!
//! So a layer's shapes, names and initialisation are written once, in the layer.
//! The initialisers are the reference's (docs/reference.md, "Initialisation").

use std::cell::RefCell;
use std::rc::Rc;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::error::Result;

/// Whether a tensor is optimised (a reference `nn.Parameter`) or a fixed buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TensorKind {
    Param,
    Buffer,
}

/// How a tensor starts in a fresh model.
#[derive(Debug, Clone, PartialEq)]
pub enum Init {
    /// U(−a, a).
    Uniform(f64),
    /// N(0, σ²).
    Normal(f64),
    Zeros,
    /// A value the layer knows from the config (graph adjacency, root mask).
    Values(Vec<f32>),
    /// Learnable edge weights of a graph layer over `adjacency` (row-major J×J): 1 on the
    /// diagonal, a jittered 0.05 on the skeleton's edges, 0 elsewhere.
    EdgeWeights(Vec<f32>),
    /// A buffer that comes from the rest pose the avatar is built for.
    Rest(RestValue),
}

/// The rest-pose-derived values of a fresh model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RestValue {
    /// The rest-pose joints: [J,3].
    Joints,
    /// The bone-alignment transforms A_j: [J,4,4].
    BoneAlign,
    /// The initial box half-extents: [J,3].
    HalfExtents,
}

impl Init {
    /// torch's default for `nn.Linear` (weights and biases): U(±1/√fan_in).
    pub fn torch_default(fan_in: usize) -> Self {
        Init::Uniform(1.0 / (fan_in as f64).sqrt())
    }

    /// SIREN's hidden-layer init U(±√(6/fan_in)/ω).
    pub fn siren(fan_in: usize, w0: f64) -> Self {
        Init::Uniform((6.0 / fan_in as f64).sqrt() / w0)
    }
}

/// Name, shape and kind of one tensor of the model, with its initialiser.
#[derive(Debug, Clone, PartialEq)]
pub struct TensorSpec {
    pub name: String,
    pub shape: Vec<usize>,
    pub kind: TensorKind,
    pub init: Init,
}

/// The values a fresh model's [`Init::Rest`] buffers take.
#[derive(Debug, Clone)]
pub struct RestValues {
    pub joints: Vec<f32>,
    pub bone_align: Vec<f32>,
    pub half_extents: Vec<f32>,
}

/// A fresh model or a layout recording: specs are collected in registration order.
struct Fresh {
    specs: Vec<TensorSpec>,
    /// `None`: record the layout only.
    init: Option<FreshInit>,
}

struct FreshInit {
    rng: ChaCha8Rng,
    rest: RestValues,
    varmap: VarMap,
    device: Device,
}

#[derive(Clone)]
enum Source<'a> {
    Load(VarBuilder<'a>),
    Fresh(Rc<RefCell<Fresh>>),
}

/// A view of the tensor source under a name prefix (see the module docs).
#[derive(Clone)]
pub struct Params<'a> {
    prefix: String,
    source: Source<'a>,
}

impl<'a> From<VarBuilder<'a>> for Params<'a> {
    fn from(vb: VarBuilder<'a>) -> Self {
        Params {
            prefix: String::new(),
            source: Source::Load(vb),
        }
    }
}

impl<'a> Params<'a> {
    /// Record names, shapes, kinds and initialisers only; the tensors handed out are zeros.
    pub fn record() -> Self {
        Self::fresh(None)
    }

    /// Draw every tensor from its initialiser with a ChaCha8 RNG seeded with `seed`, in the
    /// order the layers register them; the tensors become variables of `varmap`.
    pub fn init(seed: u64, rest: RestValues, varmap: VarMap, device: &Device) -> Self {
        Self::fresh(Some(FreshInit {
            rng: ChaCha8Rng::seed_from_u64(seed),
            rest,
            varmap,
            device: device.clone(),
        }))
    }

    fn fresh(init: Option<FreshInit>) -> Self {
        Params {
            prefix: String::new(),
            source: Source::Fresh(Rc::new(RefCell::new(Fresh {
                specs: Vec::new(),
                init,
            }))),
        }
    }

    /// The same source under `prefix.name`.
    pub fn pp(&self, name: impl ToString) -> Self {
        let name = name.to_string();
        match &self.source {
            Source::Load(vb) => Params {
                prefix: String::new(),
                source: Source::Load(vb.pp(name)),
            },
            Source::Fresh(f) => Params {
                prefix: self.full_name(&name),
                source: Source::Fresh(f.clone()),
            },
        }
    }

    /// The tensors registered so far, in registration order (empty when loading).
    pub fn specs(&self) -> Vec<TensorSpec> {
        match &self.source {
            Source::Load(_) => Vec::new(),
            Source::Fresh(f) => f.borrow().specs.clone(),
        }
    }

    /// A trained parameter.
    pub fn param(&self, shape: impl Into<Vec<usize>>, name: &str, init: Init) -> Result<Tensor> {
        self.get(shape.into(), name, TensorKind::Param, init)
    }

    /// A fixed buffer: saved with the model, never trained (returned detached).
    pub fn buffer(&self, shape: impl Into<Vec<usize>>, name: &str, init: Init) -> Result<Tensor> {
        Ok(self
            .get(shape.into(), name, TensorKind::Buffer, init)?
            .detach())
    }

    fn full_name(&self, name: &str) -> String {
        if self.prefix.is_empty() {
            name.to_string()
        } else {
            format!("{}.{name}", self.prefix)
        }
    }

    fn get(&self, shape: Vec<usize>, name: &str, kind: TensorKind, init: Init) -> Result<Tensor> {
        match &self.source {
            Source::Load(vb) => Ok(vb.get(shape, name)?),
            Source::Fresh(f) => {
                let mut f = f.borrow_mut();
                let full = self.full_name(name);
                let t = match f.init.as_mut() {
                    None => Tensor::zeros(shape.as_slice(), DType::F32, &Device::Cpu)?,
                    Some(fi) => {
                        let data = draw(&mut fi.rng, &fi.rest, &shape, &init);
                        let t = Tensor::from_vec(data, shape.as_slice(), &fi.device)?;
                        let var = Var::from_tensor(&t)?;
                        let out = var.as_tensor().clone();
                        fi.varmap
                            .data()
                            .lock()
                            .expect("fresh VarMap lock")
                            .insert(full.clone(), var);
                        out
                    }
                };
                f.specs.push(TensorSpec {
                    name: full,
                    shape,
                    kind,
                    init,
                });
                Ok(t)
            }
        }
    }
}

/// The values of one fresh tensor. The draws and their order are part of the format: a
/// seed must keep giving the same model.
fn draw(rng: &mut ChaCha8Rng, rest: &RestValues, shape: &[usize], init: &Init) -> Vec<f32> {
    let n: usize = shape.iter().product();
    match init {
        Init::Uniform(a) => (0..n).map(|_| rng.gen_range(-a..=*a) as f32).collect(),
        Init::Normal(std) => (0..n)
            .map(|_| (std * standard_normal(rng)) as f32)
            .collect(),
        Init::Zeros => vec![0.0; n],
        Init::Values(v) => v.clone(),
        Init::EdgeWeights(adj) => {
            let j = (adj.len() as f64).sqrt() as usize;
            (0..adj.len())
                .map(|i| {
                    // One draw per entry, diagonal included, so the stream does not depend
                    // on the graph.
                    let u: f64 = rng.gen();
                    if i / j == i % j {
                        1.0
                    } else {
                        adj[i] * (0.05 + 0.1 * (u - 0.5)).clamp(0.01, 1.0) as f32
                    }
                })
                .collect()
        }
        Init::Rest(RestValue::Joints) => rest.joints.clone(),
        Init::Rest(RestValue::BoneAlign) => rest.bone_align.clone(),
        Init::Rest(RestValue::HalfExtents) => rest.half_extents.clone(),
    }
}

/// Box–Muller; keeps `rand_distr` (a training-only dependency) out of inference builds.
fn standard_normal(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.gen_range(f64::EPSILON..1.0);
    let u2: f64 = rng.gen();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}
