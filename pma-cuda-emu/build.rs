//! Compiles pma-model's CUDA kernels as C for the host (src/emulate.c defines the CUDA
//! qualifiers and grid variables away), with FMA contraction off so that every product
//! and sum rounds as the kernels ask.

fn main() {
    let kernels = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../pma-model/src/compute/cuda/kernels");
    println!("cargo:rerun-if-changed=src/emulate.c");
    // A directory: cargo rebuilds when any file under it changes.
    println!("cargo:rerun-if-changed={}", kernels.display());
    cc::Build::new()
        .file("src/emulate.c")
        .include(&kernels)
        .flag_if_supported("-std=c11")
        .flag_if_supported("-ffp-contract=off")
        .warnings(true)
        .extra_warnings(true)
        .warnings_into_errors(true)
        .compile("pma_cuda_emu");
}
