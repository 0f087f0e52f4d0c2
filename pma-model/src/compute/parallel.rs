//! Data-parallel CPU workers.
//!
//! candle parallelises inside each op (gemm through rayon, large elementwise maps through
//! its barrier pool). This network is a long chain of mid-sized ops, and on a few cores the
//! per-op fork/join costs more than it gains: on a 2-core machine, two single-threaded op
//! streams together trained the paper config much faster than one stream using both cores
//! (the `throughput` example measures it). So on CPU pma runs `W` workers on disjoint chunks
//! of points or rays, each with candle's intra-op threading off. Results are combined in
//! chunk order, so they do not depend on thread timing, and for a given chunking not on `W`
//! either. The one place `W` matters: a training batch smaller than one chunk is split into
//! `W` chunks so every worker has work, and a chunked step differs from the one-pass step by
//! float summation order only (≤ 1e-6 on gradients, `tests/model/train_chunked.rs`).
//!
//! [`configure_cpu`] must run before the first candle op of the process (candle sizes its
//! thread pool once); binaries call it at start-up. Libraries and tests that never call it
//! get one worker and candle's own threading, exactly as before.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::OnceLock;

use rayon::prelude::*;

static WORKERS: AtomicUsize = AtomicUsize::new(1);

/// Use `workers` data-parallel workers (0 = one per available core) with candle's intra-op
/// threads set to 1. Respects a user's explicit `RAYON_NUM_THREADS`/`CANDLE_NUM_THREADS`:
/// then candle keeps its threads and pma uses one worker. Returns the worker count.
pub fn configure_cpu(workers: usize) -> usize {
    let user_threads = ["RAYON_NUM_THREADS", "CANDLE_NUM_THREADS"]
        .iter()
        .any(|k| std::env::var_os(k).is_some());
    if user_threads {
        WORKERS.store(1, Ordering::Relaxed);
        return 1;
    }
    let n = if workers == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        workers
    };
    if n > 1 {
        // Read by candle on every gemm and when it builds its elementwise pool. Set before any
        // other thread exists (start-up), which is what makes `set_var` sound.
        std::env::set_var("RAYON_NUM_THREADS", "1");
        std::env::set_var("CANDLE_NUM_THREADS", "1");
        keep_freed_pages();
    }
    WORKERS.store(n, Ordering::Relaxed);
    n
}

/// Tell mimalloc (the allocator of pma's binaries) to keep freed pages rather than return
/// them to the OS a second later (mimalloc v3's default). Every chunk frees and re-allocates
/// the same few hundred MB; with two workers the purges and the page faults after them are a
/// noticeable part of a training step (compare `throughput` with `MIMALLOC_PURGE_DELAY=-1`).
/// Peak RSS is set by the chunk size either way. A user's `MIMALLOC_PURGE_DELAY` wins; in a
/// process whose global allocator is not mimalloc this only configures an unused heap.
fn keep_freed_pages() {
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
        // SAFETY: mimalloc options are plain atomics, settable at any time from any thread.
        unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1) };
    }
}

/// `mi_option_purge_delay` in mimalloc.h (v2 and v3); libmimalloc-sys names no constant.
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Set the worker count without touching candle's threading (tests and benchmarks compare
/// worker counts in one process with it). Worker threads are created on first use, so a
/// count above the first one used runs on that many threads at most.
pub fn set_workers(n: usize) {
    WORKERS.store(n.max(1), Ordering::Relaxed);
}

/// The number of data-parallel workers (1 unless [`configure_cpu`] chose more).
pub fn workers() -> usize {
    WORKERS.load(Ordering::Relaxed).max(1)
}

/// Workers for tensors on `device`: GPUs parallelise inside each kernel, so work for them
/// stays on one thread (and one chunk's memory at a time), as it does on the CPU in a run
/// accounted as CUDA ([`crate::compute::account::emulates_cuda`]).
pub fn workers_on(device: &candle_core::Device) -> usize {
    if device.is_cpu() && !crate::compute::account::emulates_cuda() {
        workers()
    } else {
        1
    }
}

/// The workers: persistent threads, so allocator caches survive from one pass to the next
/// (scoped threads spawned per pass made each pass re-fault its memory).
fn pool() -> &'static rayon::ThreadPool {
    static POOL: OnceLock<rayon::ThreadPool> = OnceLock::new();
    POOL.get_or_init(|| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(workers())
            .thread_name(|i| format!("pma-worker-{i}"))
            .build()
            .expect("spawning the pma worker threads")
    })
}

/// `f(0..n)` spread over `workers` threads (at most the pool's size); results in item
/// order. Items are handed out one at a time, so uneven items balance. On failure the error
/// of the first failing item is returned, whatever the thread timing (errors are rare, so
/// finishing the other items costs nothing that matters).
pub fn map_ordered<T, E, F>(workers: usize, n: usize, f: F) -> Result<Vec<T>, E>
where
    T: Send,
    E: Send,
    F: Fn(usize) -> Result<T, E> + Sync + Send,
{
    if workers <= 1 || n <= 1 {
        return (0..n).map(f).collect();
    }
    // The workers count for the caller's accounted run, if any.
    let run = crate::compute::account::Handoff::capture();
    pool()
        .install(|| {
            (0..n)
                .into_par_iter()
                .with_max_len(1)
                .map(|i| {
                    let _joined = run.join();
                    f(i)
                })
                .collect::<Vec<Result<T, E>>>()
        })
        .into_iter()
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn map_ordered_keeps_order_and_reports_errors() {
        set_workers(3);
        let v: Result<Vec<usize>, String> = map_ordered(3, 50, |i| {
            std::thread::sleep(std::time::Duration::from_micros(
                ((i * 37) % 11) as u64 * 50,
            ));
            Ok(i * i)
        });
        assert_eq!(v.unwrap(), (0..50).map(|i| i * i).collect::<Vec<_>>());
        let e: Result<Vec<usize>, String> = map_ordered(3, 50, |i| {
            if i >= 7 {
                Err(format!("item {i}"))
            } else {
                Ok(i)
            }
        });
        assert_eq!(e.unwrap_err(), "item 7");
        set_workers(1);
    }

    #[test]
    fn purge_delay_option_index_is_mimallocs() {
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
            return;
        }
        // The untouched option reads mimalloc v3's documented default (1000 ms): the index
        // names the purge delay and not a neighbour.
        let get = || unsafe { libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY) };
        assert_eq!(get(), 1000);
        keep_freed_pages();
        assert_eq!(get(), -1);
    }
}
