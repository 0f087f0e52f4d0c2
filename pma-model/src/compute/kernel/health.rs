//! Which of pma's kernels are on in this process.
//!
//! A kernel module can fail in three ways: NVRTC rejects its source, a launch errors, or its
//! results disagree with the generic ops on random inputs ([`super::check`]), which runs
//! before its first use on a device and in `pma doctor`. Any of these switches the module
//! off for the rest of the process, with one warning line naming it and why: its ops then
//! run on candle's generic ops, slower but the same numbers within float rounding. A run
//! goes on; a training step that was under way when a backward kernel failed is retried by
//! the trainer on the generic ops.
//!
//! `--generic-kernels` ([`set_generic`]) switches every module off from the start.
//!
//! `PMA_KERNEL_FAULT` injects a failure for tests and drills, a comma-separated list of
//! `module=fault` with fault `compile` (the source does not compile: on the emulated grid
//! the first launch fails as an NVRTC error would), `launch` (every launch errors),
//! `launch@N` (launches from the N-th on error: a backward kernel mid-step) or `wrong` (the
//! kernels write zeros, which the first-use check catches).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Mutex;

use super::mem::Exec;
use super::Module;

/// What is known of a module in this process.
#[derive(Debug, Clone, PartialEq)]
pub enum State {
    /// Not used on a device yet.
    Unchecked,
    /// Its first-use check is running (the check's own calls take the kernels).
    Checking,
    /// Checked on a device, in use.
    On,
    /// Switched off: why.
    Off(String),
}

/// An injected fault (`PMA_KERNEL_FAULT`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Fault {
    Compile,
    /// Launches from this one on (1-based) error.
    Launch(u64),
    Wrong,
}

#[derive(Default)]
struct Registry {
    states: HashMap<&'static str, State>,
    launches: HashMap<&'static str, u64>,
}

static REGISTRY: Mutex<Option<Registry>> = Mutex::new(None);
static GENERIC: AtomicBool = AtomicBool::new(false);
/// Modules switched off so far in this process (a trainer retries a step that saw one).
static SWITCHED_OFF: AtomicU64 = AtomicU64::new(0);

/// Where a switch-off warning goes: stderr unless a front end installs its own line writer.
static WARN: Mutex<Option<WarningWriter>> = Mutex::new(None);

type WarningWriter = Box<dyn Fn(&str) + Send>;

thread_local! {
    /// Modules whose ops this thread runs on the generic ops for now ([`generic_for`]).
    static FORCED: std::cell::RefCell<Vec<&'static str>> = const { std::cell::RefCell::new(Vec::new()) };
}

fn with<T>(f: impl FnOnce(&mut Registry) -> T) -> T {
    let mut g = REGISTRY.lock().unwrap_or_else(|e| e.into_inner());
    f(g.get_or_insert_with(Registry::default))
}

/// Switch every module off for the process (`--generic-kernels`), or back on.
pub fn set_generic(on: bool) {
    GENERIC.store(on, Ordering::Relaxed);
}

/// Whether `--generic-kernels` is in force.
pub fn generic() -> bool {
    GENERIC.load(Ordering::Relaxed)
}

/// Send switch-off warnings to `f` instead of stderr (a progress display's line writer).
pub fn set_warning_writer(f: impl Fn(&str) + Send + 'static) {
    *WARN.lock().unwrap_or_else(|e| e.into_inner()) = Some(Box::new(f));
}

/// Run `f` with `module`'s ops on the generic route on this thread (a check's reference).
pub fn generic_for<T>(module: &'static Module, f: impl FnOnce() -> T) -> T {
    FORCED.with_borrow_mut(|v| v.push(module.name));
    let out = f();
    FORCED.with_borrow_mut(|v| {
        v.pop();
    });
    out
}

/// Whether `module`'s ops take the generic route here and now.
pub fn forced_generic(module: &'static Module) -> bool {
    generic() || FORCED.with_borrow(|v| v.contains(&module.name)) || !usable(module)
}

/// Whether `module` is not switched off.
pub fn usable(module: &'static Module) -> bool {
    !generic() && with(|r| !matches!(r.states.get(module.name), Some(State::Off(_))))
}

/// `module`'s state.
pub fn state(module: &'static Module) -> State {
    if generic() {
        return State::Off("--generic-kernels".into());
    }
    with(|r| {
        r.states
            .get(module.name)
            .cloned()
            .unwrap_or(State::Unchecked)
    })
}

/// Mark `module` as being checked before its first use on a device: `true` for the caller
/// that is to run the check (the first), `false` once it is checked or being checked.
pub fn begin_check(module: &'static Module) -> bool {
    with(|r| match r.states.get(module.name) {
        None | Some(State::Unchecked) => {
            r.states.insert(module.name, State::Checking);
            true
        }
        _ => false,
    })
}

/// The first-use check of `module` passed: it is on (unless something switched it off
/// meanwhile).
pub fn checked(module: &'static Module) {
    with(|r| {
        if r.states.get(module.name) == Some(&State::Checking) {
            r.states.insert(module.name, State::On);
        }
    })
}

/// Switch `module` off for the process, warning once with `why`.
pub fn switch_off(module: &'static Module, why: &str) {
    let first = with(|r| {
        let was_off = matches!(r.states.get(module.name), Some(State::Off(_)));
        r.states.insert(module.name, State::Off(why.to_string()));
        !was_off
    });
    if first {
        SWITCHED_OFF.fetch_add(1, Ordering::Relaxed);
        let line = format!(
            "warning: kernel {} switched off for this run ({why}); its ops run on candle's generic ops",
            module.name
        );
        match &*WARN.lock().unwrap_or_else(|e| e.into_inner()) {
            Some(w) => w(&line),
            None => eprintln!("{line}"),
        }
    }
}

/// How many modules have been switched off in this process so far.
pub fn switched_off() -> u64 {
    SWITCHED_OFF.load(Ordering::Relaxed)
}

/// A failed compile or launch of `kernel`: `module` is switched off and the error says so.
pub fn failed(module: &'static Module, kernel: &str, why: String) -> candle_core::Error {
    switch_off(module, &format!("{kernel}: {why}"));
    candle_core::Error::Msg(format!("kernel {} ({kernel}) failed: {why}", module.name))
}

/// The fault injected into `module` by `PMA_KERNEL_FAULT`, if any.
pub fn injected(module: &'static Module) -> Option<Fault> {
    static FAULTS: std::sync::OnceLock<HashMap<String, Fault>> = std::sync::OnceLock::new();
    FAULTS
        .get_or_init(|| parse_faults(&std::env::var("PMA_KERNEL_FAULT").unwrap_or_default()))
        .get(module.name)
        .copied()
}

/// `module=fault,...` (see the module docs); unknown entries are ignored with a warning.
pub fn parse_faults(spec: &str) -> HashMap<String, Fault> {
    let mut out = HashMap::new();
    for item in spec.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let fault = item.split_once('=').and_then(|(m, f)| {
            let f = match f {
                "compile" => Fault::Compile,
                "launch" => Fault::Launch(1),
                "wrong" => Fault::Wrong,
                f => Fault::Launch(
                    f.strip_prefix("launch@")?
                        .parse()
                        .ok()
                        .filter(|&n| n >= 1)?,
                ),
            };
            Some((m.to_string(), f))
        });
        match fault {
            Some((m, f)) => {
                out.insert(m, f);
            }
            None => eprintln!(
                "warning: PMA_KERNEL_FAULT entry `{item}` ignored: expected MODULE=compile|launch|launch@N|wrong"
            ),
        }
    }
    out
}

/// Before a compile of `module`: the injected compile fault.
pub fn before_compile(module: &'static Module) -> Result<(), String> {
    match injected(module) {
        Some(Fault::Compile) => Err("injected compile fault (PMA_KERNEL_FAULT)".into()),
        _ => Ok(()),
    }
}

/// Before a launch of one of `module`'s kernels on `exec`: an error for a module switched
/// off or an injected failure; `Ok(true)` when the launch must be corrupted (`wrong`).
pub fn before_launch(module: &'static Module, exec: &Exec) -> Result<bool, String> {
    if let Some(State::Off(why)) = with(|r| r.states.get(module.name).cloned()) {
        return Err(format!("switched off earlier: {why}"));
    }
    let n = with(|r| {
        let n = r.launches.entry(module.name).or_insert(0);
        *n += 1;
        *n
    });
    match injected(module) {
        // The emulated grid has no compiler: its first launch fails as a compile would.
        Some(Fault::Compile) if exec.is_host() => {
            Err("injected compile fault (PMA_KERNEL_FAULT)".into())
        }
        Some(Fault::Launch(from)) if n >= from => Err(format!(
            "injected launch fault at launch {n} (PMA_KERNEL_FAULT)"
        )),
        Some(Fault::Wrong) => Ok(true),
        _ => Ok(false),
    }
}

/// Before a CPU op of `module` runs (a forward or a backward): the injected `compile` and
/// `launch` faults, which switch `module` off and fail the op as a device kernel would.
/// (`wrong` has no effect on the CPU's code, which no first-use check covers.)
pub fn cpu_launch(module: &'static Module) -> candle_core::Result<()> {
    let Some(fault) = injected(module) else {
        return Ok(());
    };
    let n = with(|r| {
        let n = r.launches.entry(module.name).or_insert(0);
        *n += 1;
        *n
    });
    match fault {
        Fault::Compile => Err(failed(
            module,
            "cpu",
            "injected compile fault (PMA_KERNEL_FAULT)".into(),
        )),
        Fault::Launch(from) if n >= from => Err(failed(
            module,
            "cpu",
            format!("injected launch fault at launch {n} (PMA_KERNEL_FAULT)"),
        )),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn faults_parse_and_bad_entries_are_dropped() {
        let f =
            parse_faults("window_pool=launch, adam=launch@3,film_sine=wrong,rows=compile,x=boom,y");
        assert_eq!(f["window_pool"], Fault::Launch(1));
        assert_eq!(f["adam"], Fault::Launch(3));
        assert_eq!(f["film_sine"], Fault::Wrong);
        assert_eq!(f["rows"], Fault::Compile);
        assert_eq!(f.len(), 4);
        assert!(parse_faults("a=launch@0").is_empty());
    }
}
