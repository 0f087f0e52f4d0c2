//! A storage's values as an op's CPU code reads them, and what a forward keeps for its
//! backward.

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, Layout, Storage, Tensor};

/// The values of a contiguous CPU storage under `l`, of type `T` (every CPU kernel of pma
/// reads its inputs this way); `what` names the input in errors.
pub fn slice<'a, T: Values>(
    s: &'a CpuStorage,
    l: &Layout,
    what: &str,
) -> candle_core::Result<&'a [T]> {
    let Some(v) = T::of(s) else {
        candle_core::bail!("{what}: expected {}, found {:?}", T::NAME, s.dtype())
    };
    match l.contiguous_offsets() {
        // An empty view may start past its storage's end.
        Some((a, b)) if a == b => Ok(&[]),
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("{what}: expected a contiguous tensor"),
    }
}

/// The f32 values of a contiguous CPU storage under `l`.
pub fn f32_slice<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> candle_core::Result<&'a [f32]> {
    slice(s, l, what)
}

/// An element type a CPU storage may hold.
pub trait Values: Sized {
    const NAME: &'static str;
    fn of(s: &CpuStorage) -> Option<&[Self]>;
}

impl Values for f32 {
    const NAME: &'static str = "f32";
    fn of(s: &CpuStorage) -> Option<&[f32]> {
        match s {
            CpuStorage::F32(v) => Some(v),
            _ => None,
        }
    }
}

impl Values for u32 {
    const NAME: &'static str = "u32";
    fn of(s: &CpuStorage) -> Option<&[u32]> {
        match s {
            CpuStorage::U32(v) => Some(v),
            _ => None,
        }
    }
}

impl Values for u8 {
    const NAME: &'static str = "u8";
    fn of(s: &CpuStorage) -> Option<&[u8]> {
        match s {
            CpuStorage::U8(v) => Some(v),
            _ => None,
        }
    }
}

/// `f` on the f32 values of CPU tensors `ts` (each made contiguous first): a backward's
/// host code reading its inputs.
pub fn with_f32<const N: usize, R>(
    ts: [&Tensor; N],
    what: &str,
    f: impl FnOnce([&[f32]; N]) -> R,
) -> candle_core::Result<R> {
    let cs: Vec<Tensor> = ts
        .iter()
        .map(|t| t.contiguous())
        .collect::<candle_core::Result<_>>()?;
    let guards: Vec<_> = cs.iter().map(|t| t.storage_and_layout()).collect();
    let mut views = Vec::with_capacity(N);
    for (s, l) in &guards {
        let Storage::Cpu(cpu) = &**s else {
            candle_core::bail!("{what}: tensor is not on the CPU")
        };
        views.push(f32_slice(cpu, l, what)?);
    }
    let views: [&[f32]; N] = views
        .try_into()
        .map_err(|_| candle_core::Error::Msg(format!("{what}: {N} inputs expected")))?;
    Ok(f(views))
}

/// `v` as a kernel's u32 argument (`what` names it when it does not fit).
pub fn u32_of(v: usize, what: &str) -> candle_core::Result<u32> {
    u32::try_from(v)
        .map_err(|_| candle_core::Error::Msg(format!("{what} {v} exceeds a kernel's u32")))
}

/// A value a custom op's forward leaves for its backward (cos of a sine's argument, a
/// max-pool's arg-max): kept only when the graph tracks gradients, and used once, so a
/// second backward over the same graph finds it gone and computes it again.
pub struct Kept<T>(Option<std::sync::Mutex<Option<T>>>);

impl<T> Kept<T> {
    pub fn new(tracked: bool) -> Self {
        Self(tracked.then(Default::default))
    }

    /// Whether the forward should produce the value.
    pub fn wanted(&self) -> bool {
        self.0.is_some()
    }

    pub fn put(&self, v: T) {
        if let Some(m) = &self.0 {
            *m.lock().unwrap_or_else(|e| e.into_inner()) = Some(v);
        }
    }

    pub fn take(&self) -> Option<T> {
        let m = self.0.as_ref()?;
        m.lock().unwrap_or_else(|e| e.into_inner()).take()
    }
}
