//! One kernel launch, on a GPU or on the host's emulated grid.
//!
//! On CUDA the op's source is compiled once per process with NVRTC (a CUDA build then needs
//! no CUDA compiler beyond candle's, and the PTX matches the GPU it runs on) and launched on
//! the device's stream. On the host, `build.rs` compiled the same source as C with the CUDA
//! qualifiers defined away and FMA contraction off (`kernel/emulate.h`); the op's `emu.c`
//! runs a kernel once per (block, thread) of the grid, in order, taking its arguments as
//! CUDA's `kernelParams` does: an array of pointers to the values. pma's kernels are
//! grid-stride loops without shared memory or barriers, so this is what any launch of that
//! grid computes, up to the device's `sinf`/`cosf` (the C library's here) and the order of
//! `atomicAdd`s (the emulation adds in thread order).
//!
//! Both take the same grid: [`THREADS`] threads per block, one thread per element up to
//! [`MAX_BLOCKS`] blocks.

use std::ffi::{c_char, c_int, c_void, CString};

use super::mem::{Arg, Buf, Exec, Src};
use super::{health, Module};

/// The host build of a module's kernels: run kernel `name` over `blocks` × `threads` with
/// `params[i]` pointing at argument `i`; 0 on success, -1 for a kernel it does not hold.
pub type EmuFn = unsafe extern "C" fn(
    name: *const c_char,
    blocks: u32,
    threads: u32,
    params: *mut *mut c_void,
) -> c_int;

/// Threads per block of every launch.
pub const THREADS: u32 = 256;

/// The most blocks of a launch (grid-stride beyond).
pub const MAX_BLOCKS: u32 = 65_535;

thread_local! {
    /// A smaller block limit for the emulated grid ([`with_block_limit`]).
    static BLOCK_LIMIT: std::cell::Cell<Option<u32>> = const { std::cell::Cell::new(None) };
}

/// Run `f` with the emulated grid capped at `blocks` blocks, so that every thread walks
/// several elements of its grid-stride loop (a test of the loops' bounds).
pub fn with_block_limit<T>(blocks: u32, f: impl FnOnce() -> T) -> T {
    let prev = BLOCK_LIMIT.with(|c| c.replace(Some(blocks.max(1))));
    let out = f();
    BLOCK_LIMIT.with(|c| c.set(prev));
    out
}

/// Blocks for `elements` outputs.
fn blocks(elements: usize, exec: &Exec) -> u32 {
    let cap = match exec {
        Exec::Emulated => BLOCK_LIMIT.with(|c| c.get()).unwrap_or(MAX_BLOCKS),
        #[cfg(feature = "cuda")]
        Exec::Cuda(_) => MAX_BLOCKS,
    };
    elements.div_ceil(THREADS as usize).clamp(1, cap as usize) as u32
}

/// Launch `kernel` of `module` over `elements` outputs with `args` (the kernel's parameters
/// in order). Nothing runs for no elements. A failure to compile or launch switches
/// `module` off ([`health`]) before it is returned; an injected fault (`PMA_KERNEL_FAULT`)
/// fails or corrupts the launch as asked.
pub fn launch(
    exec: &Exec,
    module: &'static Module,
    kernel: &'static str,
    elements: usize,
    args: &mut [Arg],
) -> candle_core::Result<()> {
    if elements == 0 {
        return Ok(());
    }
    let wrong = match health::before_launch(module, exec) {
        Ok(wrong) => wrong,
        Err(why) => return Err(health::failed(module, kernel, why)),
    };
    let grid = blocks(elements, exec);
    let run = match exec {
        Exec::Emulated => emulated(module, kernel, grid, args),
        #[cfg(feature = "cuda")]
        Exec::Cuda(dev) => cuda::launch(dev, module, kernel, grid, args),
    };
    if let Err(e) = run {
        return Err(health::failed(module, kernel, e.to_string()));
    }
    if wrong {
        // The injected "wrong" fault: the kernel's outputs read as zeros.
        for a in args.iter_mut() {
            if let Arg::Dst(b) = a {
                zero(exec, b)?;
            }
        }
    }
    Ok(())
}

fn zero(exec: &Exec, b: &mut Buf) -> candle_core::Result<()> {
    match (exec, b) {
        (_, Buf::F32(v)) => v.fill(0.0),
        (_, Buf::U32(v)) => v.fill(0),
        #[cfg(feature = "cuda")]
        (Exec::Cuda(d), Buf::CudaF32(s)) => {
            use candle_core::cuda_backend::WrapErr;
            d.cuda_stream().memset_zeros(s).w()?
        }
        #[cfg(feature = "cuda")]
        (Exec::Cuda(d), Buf::CudaU32(s)) => {
            use candle_core::cuda_backend::WrapErr;
            d.cuda_stream().memset_zeros(s).w()?
        }
        #[cfg(feature = "cuda")]
        _ => candle_core::bail!("a GPU buffer on the emulated grid"),
    }
    Ok(())
}

/// One parameter as CUDA's `kernelParams` points at it: a buffer's address or a scalar.
#[repr(C)]
union Param {
    ptr: *mut c_void,
    u: u32,
    i: i32,
    f: f32,
}

/// `kernel` over `blocks` × [`THREADS`] on the host.
fn emulated(
    module: &'static Module,
    kernel: &'static str,
    blocks: u32,
    args: &mut [Arg],
) -> candle_core::Result<()> {
    let mut params = Vec::with_capacity(args.len());
    for a in args.iter_mut() {
        params.push(match a {
            Arg::Src(Src::F32(v)) => Param {
                ptr: v.as_ptr() as *mut c_void,
            },
            Arg::Src(Src::U32(v)) => Param {
                ptr: v.as_ptr() as *mut c_void,
            },
            Arg::Src(Src::U8(v)) => Param {
                ptr: v.as_ptr() as *mut c_void,
            },
            Arg::Dst(Buf::F32(v)) => Param {
                ptr: v.as_mut_ptr().cast(),
            },
            Arg::Dst(Buf::U32(v)) => Param {
                ptr: v.as_mut_ptr().cast(),
            },
            Arg::U32(v) => Param { u: *v },
            Arg::I32(v) => Param { i: *v },
            Arg::F32(v) => Param { f: *v },
            #[cfg(feature = "cuda")]
            _ => candle_core::bail!("{kernel}: GPU memory on the emulated grid"),
        });
    }
    let mut ptrs: Vec<*mut c_void> = params
        .iter_mut()
        .map(|p| (p as *mut Param).cast())
        .collect();
    let name = CString::new(kernel).map_err(|e| candle_core::Error::Msg(e.to_string()))?;
    // SAFETY: `ptrs[i]` points at argument i, which lives until the call returns; the op
    // built `args` in the kernel's parameter order with buffers at least as long as the
    // kernel indexes (its shapes were checked), as on a GPU.
    let rc = unsafe { (module.emulate)(name.as_ptr(), blocks, THREADS, ptrs.as_mut_ptr()) };
    if rc != 0 {
        candle_core::bail!("{kernel}: no such kernel in {}", module.file)
    }
    Ok(())
}

#[cfg(feature = "cuda")]
mod cuda {
    use std::collections::HashMap;
    use std::sync::Mutex;

    use candle_core::cuda_backend::cudarc::driver::{LaunchConfig, PushKernelArg};
    use candle_core::cuda_backend::{CudaDevice, WrapErr};

    use super::super::health;
    use super::super::mem::{Arg, Buf, Src};
    use super::super::Module;

    /// PTX of each module, compiled once per process (or the compile error, kept).
    static PTX: Mutex<Option<HashMap<&'static str, Result<&'static str, String>>>> =
        Mutex::new(None);

    /// PTX of `module`, compiled with NVRTC on first use.
    pub(super) fn ptx(module: &'static Module) -> Result<&'static str, String> {
        let mut cache = PTX.lock().unwrap_or_else(|e| e.into_inner());
        let cache = cache.get_or_insert_with(HashMap::new);
        cache
            .entry(module.name)
            .or_insert_with(|| {
                health::before_compile(module)?;
                candle_core::cuda_backend::cudarc::nvrtc::compile_ptx(module.source)
                    .map(|p| &*Box::leak(p.to_src().into_boxed_str()))
                    .map_err(|e| format!("NVRTC rejected pma-model/src/{}: {e}", module.file))
            })
            .clone()
    }

    pub(super) fn launch(
        dev: &CudaDevice,
        module: &'static Module,
        kernel: &'static str,
        blocks: u32,
        args: &mut [Arg],
    ) -> candle_core::Result<()> {
        let ptx = ptx(module).map_err(candle_core::Error::Msg)?;
        let func = dev.get_or_load_custom_func(kernel, &format!("pma_{}", module.name), ptx)?;
        let mut b = func.builder();
        for a in args.iter() {
            match a {
                Arg::Src(Src::CudaF32(v)) => b.arg(v),
                Arg::Src(Src::CudaU32(v)) => b.arg(v),
                Arg::Src(Src::CudaU8(v)) => b.arg(v),
                Arg::Dst(Buf::CudaF32(s)) => b.arg(s),
                Arg::Dst(Buf::CudaU32(s)) => b.arg(s),
                Arg::U32(v) => b.arg(v),
                Arg::I32(v) => b.arg(v),
                Arg::F32(v) => b.arg(v),
                _ => candle_core::bail!("{kernel}: host memory in a CUDA launch"),
            };
        }
        let cfg = LaunchConfig {
            grid_dim: (blocks, 1, 1),
            block_dim: (super::THREADS, 1, 1),
            shared_mem_bytes: 0,
        };
        // SAFETY: the op built `args` in the kernel's parameter order, with buffers at least
        // as long as the kernel indexes (its shapes were checked), on this device's stream.
        unsafe { b.launch(cfg) }.w()?;
        Ok(())
    }
}

/// The NVRTC compile of `module` on this process's first use, for `pma doctor`: `Ok` with
/// the PTX's length, or the compiler's message. `None` without CUDA.
pub fn compile(module: &'static Module) -> Option<Result<usize, String>> {
    #[cfg(feature = "cuda")]
    {
        Some(cuda::ptx(module).map(str::len))
    }
    #[cfg(not(feature = "cuda"))]
    {
        let _ = module;
        None
    }
}
