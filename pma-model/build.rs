//! Compiles pma's CUDA kernels for the host's emulated grid: each op's `emu.c` includes
//! `compute/kernel/emulate.h` (the CUDA qualifiers defined away, then `prelude.cuh`) and the
//! op's `.cu` source.
//! FMA contraction is off, so every product and sum rounds as the kernels ask.

use std::path::Path;

fn main() {
    let ops = Path::new("src/compute/ops");
    println!("cargo:rerun-if-changed=src/compute/kernel/emulate.h");
    println!("cargo:rerun-if-changed=src/compute/kernel/prelude.cuh");
    let mut build = cc::Build::new();
    let mut dirs: Vec<_> = std::fs::read_dir(ops)
        .expect("src/compute/ops")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("emu.c").is_file())
        .collect();
    dirs.sort();
    for dir in &dirs {
        // A directory: cargo rebuilds when any file under it changes.
        println!("cargo:rerun-if-changed={}", dir.display());
        build.file(dir.join("emu.c"));
    }
    build
        .flag_if_supported("-std=c11")
        .flag_if_supported("-ffp-contract=off")
        .warnings(true)
        .extra_warnings(true)
        .warnings_into_errors(true)
        .compile("pma_kernels_emulated");
}
