//! Choosing the compute device from a command-line string, and what the device offers.
//!
//! Lives in the model crate (not the CLI) so that the inference-only binary, which has no
//! CLI framework, parses `--device` the same way as `pma`.

use candle_core::Device;

/// Why a device string could not be turned into a [`Device`].
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    #[error("unknown device `{0}`: expected cpu, cuda, cuda:N, metal or metal:N")]
    Unknown(String),

    /// A device list names one GPU twice.
    #[error("device list `{spec}`: `{name}` appears twice (each rank needs its own GPU)")]
    Repeated { spec: String, name: String },

    /// The binary was built without the backend; say which cargo feature brings it, since
    /// that is the only fix.
    #[error("device `{spec}` needs a binary built with `--features {feature}` (this one was not)")]
    NotCompiled { spec: String, feature: &'static str },

    /// The backend is compiled in but the device could not be opened (no GPU, driver or
    /// library missing, ordinal out of range).
    #[error("device `{spec}`: {source}")]
    Open {
        spec: String,
        #[source]
        source: candle_core::Error,
    },
}

impl pma_data::ExitKind for DeviceError {
    fn kind(&self) -> pma_data::ErrorKind {
        match self {
            DeviceError::Unknown(_)
            | DeviceError::Repeated { .. }
            | DeviceError::NotCompiled { .. } => pma_data::ErrorKind::Refused,
            // A device that exists in the build but cannot be opened (no GPU, a driver error).
            DeviceError::Open { .. } => pma_data::ErrorKind::Failure,
        }
    }
}

impl pma_data::ExitKind for Tf32Error {
    fn kind(&self) -> pma_data::ErrorKind {
        pma_data::ErrorKind::Refused
    }
}

impl pma_data::ExitKind for Bf16Error {
    fn kind(&self) -> pma_data::ErrorKind {
        pma_data::ErrorKind::Refused
    }
}

/// Parse `cpu`, `cuda`, `cuda:N`, `metal` or `metal:N` (case-insensitive) and open it.
pub fn parse_device(spec: &str) -> Result<Device, DeviceError> {
    let s = spec.trim().to_ascii_lowercase();
    let (kind, ordinal) = match s.split_once(':') {
        Some((k, n)) => {
            let n: usize = n
                .parse()
                .map_err(|_| DeviceError::Unknown(spec.to_string()))?;
            (k.to_string(), n)
        }
        None => (s.clone(), 0),
    };
    let open = |r: candle_core::Result<Device>| {
        r.map_err(|source| DeviceError::Open {
            spec: spec.to_string(),
            source,
        })
    };
    match kind.as_str() {
        "cpu" if !s.contains(':') => Ok(Device::Cpu),
        "cuda" => {
            if !candle_core::utils::cuda_is_available() {
                return Err(DeviceError::NotCompiled {
                    spec: spec.to_string(),
                    feature: "cuda",
                });
            }
            let dev = open(Device::new_cuda(ordinal))?;
            keep_pool_memory(&dev).map_err(|source| DeviceError::Open {
                spec: spec.to_string(),
                source,
            })?;
            Ok(dev)
        }
        "metal" => {
            if !candle_core::utils::metal_is_available() {
                return Err(DeviceError::NotCompiled {
                    spec: spec.to_string(),
                    feature: "metal",
                });
            }
            open(Device::new_metal(ordinal))
        }
        _ => Err(DeviceError::Unknown(spec.to_string())),
    }
}

/// Parse a list of devices for a data-parallel group: `cpu,cpu`, `cuda:0,1,2,3` (a bare
/// ordinal after `cuda:N` or `metal:N` is another device of that kind) or any comma-separated
/// list of [`parse_device`]'s forms. One entry is one device. Refused: an empty entry, or
/// the same GPU twice (two ranks cannot share one).
pub fn parse_devices(spec: &str) -> Result<Vec<Device>, DeviceError> {
    let mut kind: Option<String> = None;
    let mut names = Vec::new();
    for part in spec.split(',') {
        let part = part.trim().to_ascii_lowercase();
        let name = match (&kind, part.parse::<usize>()) {
            (Some(k), Ok(n)) => format!("{k}:{n}"),
            _ if part == "cuda" || part == "metal" => format!("{part}:0"),
            _ => part.clone(),
        };
        if name.is_empty() || part.parse::<usize>().is_ok() && kind.is_none() {
            return Err(DeviceError::Unknown(spec.to_string()));
        }
        kind = name.split_once(':').map(|(k, _)| k.to_string());
        if name != "cpu" && names.contains(&name) {
            return Err(DeviceError::Repeated {
                spec: spec.to_string(),
                name,
            });
        }
        names.push(name);
    }
    names.iter().map(|n| parse_device(n)).collect()
}

/// Keep freed GPU memory in the stream-ordered pool instead of handing it back to the driver.
///
/// cudarc allocates with `cuMemAllocAsync` from the device's pool, whose release threshold
/// is 0: every synchronisation returns the pool's free memory to the driver, and the next
/// step allocates it again. A threshold of `u64::MAX` keeps it (the peak of one training
/// step stays reserved, as PyTorch's caching allocator does).
#[cfg(feature = "cuda")]
fn keep_pool_memory(dev: &Device) -> candle_core::Result<()> {
    use candle_core::cuda_backend::cudarc::driver::{result, sys};
    use candle_core::cuda_backend::WrapErr;
    let Device::Cuda(cuda) = dev else {
        return Ok(());
    };
    let cu_device = cuda.cuda_stream().context().cu_device();
    let mut threshold: u64 = u64::MAX;
    // SAFETY: `cu_device` comes from a live context; the attribute takes a cuuint64_t.
    unsafe {
        let pool = result::device::get_mem_pool(cu_device).w()?;
        result::mem_pool::set_attribute(
            pool,
            sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_RELEASE_THRESHOLD,
            (&mut threshold as *mut u64).cast(),
        )
        .w()?;
    }
    Ok(())
}

#[cfg(not(feature = "cuda"))]
fn keep_pool_memory(_dev: &Device) -> candle_core::Result<()> {
    Ok(())
}

/// Free memory of `device` in bytes (`cuMemGetInfo`), or `None` for the CPU and other
/// devices (and when the driver cannot tell). Memory the stream-ordered pool keeps for reuse
/// counts as used, so ask before the first step allocates. A CPU run accounted as CUDA gets
/// the free memory it models ([`crate::compute::account::Account::model_free_memory`]).
pub fn free_memory(device: &Device) -> Option<usize> {
    if device.is_cpu() {
        return crate::compute::account::modeled_free_memory();
    }
    cuda_free_memory(device)
}

#[cfg(feature = "cuda")]
fn cuda_free_memory(device: &Device) -> Option<usize> {
    use candle_core::cuda_backend::cudarc::driver::result;
    let Device::Cuda(cuda) = device else {
        return None;
    };
    // The query reads the calling thread's current context.
    cuda.cuda_stream().context().bind_to_thread().ok()?;
    result::mem_get_info().ok().map(|(free, _total)| free)
}

#[cfg(not(feature = "cuda"))]
fn cuda_free_memory(_device: &Device) -> Option<usize> {
    None
}

/// Bytes of device memory a training step's chunk holds per point × joint × feature element
/// (an estimate). The step account counts 19.9 on the CUDA route (the `default` step's peak of
/// live memory at 128 and 512 rays per chunk: 0.59 and 2.28 GB); it does not see the caching
/// allocator's slack, cuBLAS's workspace or a custom op's transient product (4 bytes per
/// element for the widest layer's), hence 32, checked against the count by
/// `tests/model/account.rs`. A chunk the estimate gets wrong runs out of memory and is halved
/// and retried ([`is_out_of_memory`]). An inference call keeps at most its forward's share of
/// it, so it bounds that too.
pub const BYTES_PER_ELEMENT: usize = 32;

/// Share of the free device memory automatic chunks are sized to; the rest is headroom for
/// the allocator, cuBLAS's workspace and what the estimate misses.
pub const DEVICE_MEMORY_SHARE: f64 = 0.8;

/// How many points × joints × features [`DEVICE_MEMORY_SHARE`] of `device`'s free memory
/// holds at [`BYTES_PER_ELEMENT`]; `None` where pma does not size work from device memory
/// (the CPU).
pub fn element_budget(device: &Device) -> Option<usize> {
    free_memory(device).map(|free| (free as f64 * DEVICE_MEMORY_SHARE) as usize / BYTES_PER_ELEMENT)
}

/// Whether an error (its whole message, causes included) is a device running out of
/// memory: a CUDA allocation that failed, or the fault `PMA_FAULT_OOM_RAYS` injects.
pub fn is_out_of_memory(message: &str) -> bool {
    message.contains("CUDA_ERROR_OUT_OF_MEMORY") || message.contains("out of device memory")
}

/// The injected allocation failure of `PMA_FAULT_OOM_RAYS=N` (tests and drills): a training
/// chunk of more than N rays fails as a device running out of memory would.
pub fn injected_oom(rays: usize) -> candle_core::Result<()> {
    static LIMIT: std::sync::OnceLock<Option<usize>> = std::sync::OnceLock::new();
    let limit = LIMIT.get_or_init(|| {
        std::env::var("PMA_FAULT_OOM_RAYS")
            .ok()?
            .trim()
            .parse()
            .ok()
    });
    match *limit {
        Some(n) if rays > n => candle_core::bail!(
            "out of device memory (injected by PMA_FAULT_OOM_RAYS={n}) for a chunk of {rays} rays"
        ),
        _ => Ok(()),
    }
}

/// What a device is, for a report (`pma doctor`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct DeviceInfo {
    /// `cpu`, `cuda:N` or `metal:N`.
    pub spec: String,
    /// The GPU's name, or the CPU's model (from /proc/cpuinfo where there is one).
    pub name: String,
    pub memory_total_bytes: Option<u64>,
    pub memory_free_bytes: Option<u64>,
    /// The CUDA driver's version (e.g. `13.0`).
    pub driver: Option<String>,
    /// The NVRTC library's version, which compiles pma's kernels at run time.
    pub nvrtc: Option<String>,
    /// A GPU's compute capability (major, minor).
    pub compute_capability: Option<(u32, u32)>,
    /// CPU cores this process may use.
    pub cores: usize,
}

/// Describe `device` (what the driver and the OS tell; missing items stay `None`).
pub fn describe(device: &Device) -> DeviceInfo {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut info = DeviceInfo {
        spec: match device.location() {
            candle_core::DeviceLocation::Cpu => "cpu".into(),
            candle_core::DeviceLocation::Cuda { gpu_id } => format!("cuda:{gpu_id}"),
            candle_core::DeviceLocation::Metal { gpu_id } => format!("metal:{gpu_id}"),
        },
        name: cpu_model().unwrap_or_else(|| std::env::consts::ARCH.to_string()),
        memory_total_bytes: host_memory_kib("MemTotal:").map(|k| k * 1024),
        memory_free_bytes: host_memory_kib("MemAvailable:").map(|k| k * 1024),
        driver: None,
        nvrtc: None,
        compute_capability: None,
        cores,
    };
    describe_cuda(device, &mut info);
    info
}

fn cpu_model() -> Option<String> {
    let text = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("model name"))?;
    Some(line.split_once(':')?.1.trim().to_string())
}

fn host_memory_kib(key: &str) -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with(key))?;
    line[key.len()..]
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

#[cfg(feature = "cuda")]
fn describe_cuda(device: &Device, info: &mut DeviceInfo) {
    use candle_core::cuda_backend::cudarc::driver::{result, sys};
    use candle_core::cuda_backend::cudarc::nvrtc;
    let Device::Cuda(cuda) = device else {
        return;
    };
    let cu = cuda.cuda_stream().context().cu_device();
    if let Ok(name) = result::device::get_name(cu) {
        info.name = name;
    }
    // SAFETY: `cu` comes from a live context.
    info.memory_total_bytes = unsafe { result::device::total_mem(cu) }
        .ok()
        .map(|b| b as u64);
    info.memory_free_bytes = cuda_free_memory(device).map(|b| b as u64);
    use sys::CUdevice_attribute::{
        CU_DEVICE_ATTRIBUTE_COMPUTE_CAPABILITY_MAJOR as MAJOR,
        CU_DEVICE_ATTRIBUTE_COMPUTE_CAPABILITY_MINOR as MINOR,
    };
    // SAFETY: `cu` comes from a live context.
    let attribute = |a| unsafe { result::device::get_attribute(cu, a) }.ok();
    if let (Some(major), Some(minor)) = (attribute(MAJOR), attribute(MINOR)) {
        info.compute_capability = Some((major as u32, minor as u32));
    }
    let mut v: std::ffi::c_int = 0;
    // SAFETY: the driver writes one int.
    if unsafe { sys::cuDriverGetVersion(&mut v) } == sys::CUresult::CUDA_SUCCESS {
        info.driver = Some(format!("{}.{}", v / 1000, (v % 1000) / 10));
    }
    let (mut major, mut minor): (std::ffi::c_int, std::ffi::c_int) = (0, 0);
    // SAFETY: NVRTC writes two ints.
    if unsafe { nvrtc::sys::nvrtcVersion(&mut major, &mut minor) }
        == nvrtc::sys::nvrtcResult::NVRTC_SUCCESS
    {
        info.nvrtc = Some(format!("{major}.{minor}"));
    }
}

#[cfg(not(feature = "cuda"))]
fn describe_cuda(_device: &Device, _info: &mut DeviceInfo) {}

/// Why `--tf32` was refused.
#[derive(Debug, thiserror::Error)]
#[error("--tf32 needs a CUDA device (this run is on {device}): TF32 is a mode of the GPU's tensor cores, the CPU always computes in full f32")]
pub struct Tf32Error {
    pub device: String,
}

/// Whether TF32 (`--tf32`, [`crate::compute::numerics::Numerics::tf32`]) can be asked for on
/// `device`: refused on a device other than CUDA, where it would do nothing.
pub fn check_tf32(on: bool, device: &Device) -> Result<(), Tf32Error> {
    if on && !device.is_cuda() {
        return Err(Tf32Error {
            device: if device.is_metal() {
                "metal"
            } else {
                "the cpu"
            }
            .to_string(),
        });
    }
    Ok(())
}

/// The least compute capability with candle's f32 ↔ bf16 casts (candle-kernels defines them
/// for sm_80 and later: docs/gpu.md, "What candle's CUDA backend must implement").
pub const BF16_MIN_CAPABILITY: (u32, u32) = (8, 0);

/// Why `--bf16-trunk` was refused.
#[derive(Debug, thiserror::Error)]
#[error("--bf16-trunk needs a GPU of compute capability {}.{} or later for its bf16 casts ({spec} is {}.{}); run without it", BF16_MIN_CAPABILITY.0, BF16_MIN_CAPABILITY.1, .capability.0, .capability.1)]
pub struct Bf16Error {
    pub spec: String,
    pub capability: (u32, u32),
}

/// Whether the bf16 trunk ([`crate::compute::numerics::Numerics::bf16_trunk`]) can run on
/// `device`: refused on a GPU whose compute capability is known and under
/// [`BF16_MIN_CAPABILITY`], which would otherwise stop at the first cast of a run. The CPU
/// emulates it.
pub fn check_bf16_trunk(on: bool, device: &Device) -> Result<(), Bf16Error> {
    if !on || !device.is_cuda() {
        return Ok(());
    }
    let info = describe(device);
    bf16_capability(&info.spec, info.compute_capability)
}

fn bf16_capability(spec: &str, capability: Option<(u32, u32)>) -> Result<(), Bf16Error> {
    match capability {
        Some(c) if c < BF16_MIN_CAPABILITY => Err(Bf16Error {
            spec: spec.to_string(),
            capability: c,
        }),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_and_bad_specs() {
        assert!(matches!(parse_device("cpu"), Ok(Device::Cpu)));
        assert!(matches!(parse_device(" CPU "), Ok(Device::Cpu)));
        for bad in ["", "tpu", "cpu:0", "cuda:x", "cuda:-1", "metal:"] {
            assert!(
                matches!(parse_device(bad), Err(DeviceError::Unknown(_))),
                "{bad}"
            );
        }
    }

    #[test]
    fn bf16_trunk_is_refused_under_sm_80() {
        let e = bf16_capability("cuda:0", Some((7, 5)))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--bf16-trunk needs a GPU of compute capability 8.0"),
            "{e}"
        );
        assert!(e.contains("cuda:0 is 7.5"), "{e}");
        assert!(bf16_capability("cuda:0", Some((8, 0))).is_ok());
        assert!(bf16_capability("cuda:0", Some((9, 0))).is_ok());
        assert!(bf16_capability("cuda:0", None).is_ok());
        assert!(check_bf16_trunk(true, &Device::Cpu).is_ok());
    }

    #[test]
    fn device_lists() {
        let cpus = parse_devices("cpu, CPU").unwrap();
        assert_eq!(cpus.len(), 2);
        assert!(cpus.iter().all(Device::is_cpu));
        assert_eq!(parse_devices("cpu").unwrap().len(), 1);
        for bad in ["", "cpu,", ",cpu", "0,1", "cpu,1", "cpu,tpu"] {
            assert!(
                matches!(parse_devices(bad), Err(DeviceError::Unknown(_))),
                "{bad}"
            );
        }
        for twice in ["cuda:0,0", "cuda,cuda:0", "metal:1,metal:1"] {
            assert!(
                matches!(parse_devices(twice), Err(DeviceError::Repeated { .. })),
                "{twice}"
            );
        }
        if !candle_core::utils::cuda_is_available() {
            let e = parse_devices("cuda:0,1").unwrap_err();
            assert!(e.to_string().contains("cuda:0"), "{e}");
        }
    }

    #[test]
    fn tf32_is_refused_off_cuda() {
        let e = check_tf32(true, &Device::Cpu).unwrap_err().to_string();
        assert!(e.contains("--tf32 needs a CUDA device"), "{e}");
        assert!(check_tf32(false, &Device::Cpu).is_ok());
    }

    #[test]
    fn missing_backend_names_the_feature() {
        if !candle_core::utils::cuda_is_available() {
            let e = parse_device("cuda:1").unwrap_err();
            assert!(e.to_string().contains("--features cuda"), "{e}");
        }
        if !candle_core::utils::metal_is_available() {
            let e = parse_device("metal").unwrap_err();
            assert!(e.to_string().contains("--features metal"), "{e}");
        }
    }
}
