//! Choosing the compute device from a command-line string.
//!
//! Lives in the model crate (not the CLI) so that the inference-only binary, which has no
//! CLI framework, parses `--device` the same way as `pma`.

use candle_core::Device;

/// Why a device string could not be turned into a [`Device`].
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    #[error("unknown device `{0}`: expected cpu, cuda, cuda:N, metal or metal:N")]
    Unknown(String),

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
            open(Device::new_cuda(ordinal))
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
