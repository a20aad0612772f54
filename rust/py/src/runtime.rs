//! Calling into the core from Python: rayon pools by thread count (built once), the GIL
//! released while Rust works, `RasterError`s mapped to `ValueError`s and panics to
//! `RuntimeError`s instead of crossing into Python. Apart from the bindings, which only say what
//! to run.
//!
//! `threads = 1` runs on the calling thread itself, `threads = T > 1` on a pool of T workers
//! (the caller sleeps meanwhile), `threads = 0` on a pool of rayon's default size
//! (`RAYON_NUM_THREADS`, else the cores the process may use). So a process that passes T to
//! every call has T busy threads in all. Measured (issue 51): a `fit --threads 1` (200
//! iterations of the embedded scene) through a one-worker pool kept that worker at 16 % of the
//! process's CPU time (4.4 of 27.8 s) while the Python thread slept: serial, but two busy
//! threads to `top -H` and a hand-off (two wake-ups) per call; inline, all its CPU time is
//! the Python thread's and a small call takes 40 instead of 65 us.

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::collections::HashMap;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock, PoisonError};
use sync4d_raster::{self as core, RasterError};

/// Rayon pools by thread count, built once and reused (0: rayon's default count). Not rayon's
/// global pool for 0: a thread that ran a `threads = 1` call is the worker of its own one-thread
/// pool (`SERIAL`), where a bare `par_iter` would stay on that thread.
fn pool(threads: usize) -> PyResult<Arc<rayon::ThreadPool>> {
    static POOLS: OnceLock<Mutex<HashMap<usize, Arc<rayon::ThreadPool>>>> = OnceLock::new();
    let mut pools = lock(
        POOLS.get_or_init(|| Mutex::new(HashMap::new())),
        "thread-pool registry",
    )?;
    if let Some(p) = pools.get(&threads) {
        return Ok(p.clone());
    }
    let p = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| {
            PyRuntimeError::new_err(format!("sync4d: cannot start {threads} threads: {e}"))
        })?;
    let p = Arc::new(p);
    pools.insert(threads, p.clone());
    Ok(p)
}

thread_local! {
    /// This thread's one-thread pool whose only worker is the thread itself
    /// (`use_current_thread`): `install` runs inline and the parallel iterators in it run
    /// serially here. Never dropped (a clone is forgotten; rayon leaks such a registry anyway),
    /// so no rayon code runs in a thread-local destructor. None when the thread is a rayon
    /// worker already.
    static SERIAL: Option<Arc<rayon::ThreadPool>> = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .use_current_thread()
        .build()
        .ok()
        .map(|p| {
            let p = Arc::new(p);
            std::mem::forget(p.clone());
            p
        });
}

/// Run `f` without the GIL on a pool of `threads` threads, mapping errors and panics.
pub(crate) fn run<T: Send>(
    py: Python<'_>,
    threads: usize,
    f: impl FnOnce() -> core::Result<T> + Send,
) -> PyResult<T> {
    // allow_threads runs `f` on this same thread, so there the serial pool's worker is the
    // caller and `install` runs `f` inline.
    let serial = if threads == 1 {
        SERIAL.with(Clone::clone)
    } else {
        None
    };
    let pool = match serial {
        Some(p) => p,
        None => pool(threads)?,
    };
    let out = py.allow_threads(move || catch_unwind(AssertUnwindSafe(move || pool.install(f))));
    match out {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(to_py(e)),
        Err(panic) => {
            let msg = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(ToString::to_string))
                .unwrap_or_else(|| "unknown panic".into());
            Err(PyRuntimeError::new_err(format!(
                "sync4d rasterizer internal error (please report with the inputs that caused it): {msg}"
            )))
        }
    }
}

/// Lock `m`, a poisoned lock (a panic while another call held it) being a `RuntimeError`
/// "sync4d: {what} poisoned": for state that a half-finished update may leave inconsistent.
pub(crate) fn lock<'a, T>(m: &'a Mutex<T>, what: &str) -> PyResult<MutexGuard<'a, T>> {
    m.lock()
        .map_err(|_| PyRuntimeError::new_err(format!("sync4d: {what} poisoned")))
}

/// Lock `m`, recovering a poisoned lock (`PoisonError::into_inner`) instead of erroring: for
/// state that every call overwrites or that stays usable after a panic (the rasterizers and
/// their reusable buffers; the panic itself was already reported as a `RuntimeError`).
pub(crate) fn lock_recover<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

pub(crate) fn to_py(e: RasterError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// Number of threads a call with `threads = 0` uses (rayon's default count).
#[pyfunction]
pub(crate) fn default_threads() -> PyResult<usize> {
    Ok(pool(0)?.current_num_threads())
}
