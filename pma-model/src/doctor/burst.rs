//! A short training burst on the device: steps per second and peak memory.

use std::sync::Arc;
use std::time::Instant;

use candle_core::Device;
use serde::Serialize;

use crate::train::{Preset, RunConfig, Trainer};

/// What the burst measured.
#[derive(Debug, Clone, Serialize)]
pub struct Burst {
    pub preset: String,
    pub steps: usize,
    pub rays_per_step: usize,
    /// Rays per chunk the trainer chose (`chunk_rays = 0`: from the device's free memory on a
    /// GPU).
    pub chunk_rays: usize,
    /// Steps after the first (which compiles kernels and fills caches) per second of wall time.
    pub it_per_s: f64,
    /// The first step's wall seconds.
    pub first_step_s: f64,
    /// On a GPU: the device's total memory less the least free memory seen after a step (the
    /// memory pool keeps what a step allocated); on the CPU: the process's peak RSS.
    pub peak_memory_bytes: Option<u64>,
}

/// `steps` training steps of `preset` on the embedded synthetic scene (4 cameras × 4
/// frames, 96 px), made in memory.
pub fn run(device: &Device, preset: Preset, steps: usize) -> Result<Burst, String> {
    let synth = pma_data::synth::SynthConfig::small(96, 4, 4);
    let plan = pma_data::synth::plan(&synth).map_err(|e| e.to_string())?;
    let data = pma_data::synth::render_split(&plan, &plan.splits[0], &mut || {})
        .map_err(|e| e.to_string())?;
    let run = RunConfig::from_preset(preset);
    let rays_per_step = run.train.rays_per_step;
    let mut trainer = Trainer::new(run, Arc::new(data), device).map_err(|e| e.to_string())?;
    let memory = || peak_memory(device);
    let clock = Instant::now();
    trainer.step_read().map_err(|e| e.to_string())?;
    let first_step_s = clock.elapsed().as_secs_f64();
    let mut peak = memory();
    let clock = Instant::now();
    for _ in 1..steps {
        trainer.step().map_err(|e| e.to_string())?;
        peak = peak.max(memory());
    }
    trainer.read_back().map_err(|e| e.to_string())?;
    let rest = clock.elapsed().as_secs_f64();
    Ok(Burst {
        preset: preset.name().to_string(),
        steps,
        rays_per_step,
        chunk_rays: trainer.chunk_rays().min(rays_per_step),
        it_per_s: if steps > 1 {
            (steps - 1) as f64 / rest
        } else {
            1.0 / first_step_s
        },
        first_step_s,
        peak_memory_bytes: peak,
    })
}

fn peak_memory(device: &Device) -> Option<u64> {
    if device.is_cpu() {
        let status = std::fs::read_to_string("/proc/self/status").ok()?;
        let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
        let kib: u64 = line["VmHWM:".len()..]
            .trim()
            .trim_end_matches("kB")
            .trim()
            .parse()
            .ok()?;
        return Some(kib * 1024);
    }
    let info = crate::compute::device::describe(device);
    Some(
        info.memory_total_bytes?
            .saturating_sub(info.memory_free_bytes?),
    )
}
