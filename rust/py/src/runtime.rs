//! Calling into the core from Python: rayon pools by thread count (built once), the GIL
//! released while Rust works, `RasterError`s mapped to `ValueError`s and panics to
//! `RuntimeError`s instead of crossing into Python. Apart from the bindings, which only say what
//! to run.

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::collections::HashMap;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Mutex, OnceLock};
use sync4d_raster::{self as core, RasterError};

/// Rayon pools by thread count, built once and reused (0 = rayon's global pool).
fn pool(threads: usize) -> PyResult<Option<Arc<rayon::ThreadPool>>> {
    if threads == 0 {
        return Ok(None);
    }
    static POOLS: OnceLock<Mutex<HashMap<usize, Arc<rayon::ThreadPool>>>> = OnceLock::new();
    let mut pools = POOLS
        .get_or_init(|| Mutex::new(HashMap::new()))
        .lock()
        .map_err(|_| PyRuntimeError::new_err("sync4d: thread-pool registry poisoned"))?;
    if let Some(p) = pools.get(&threads) {
        return Ok(Some(p.clone()));
    }
    let p = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| {
            PyRuntimeError::new_err(format!("sync4d: cannot start {threads} threads: {e}"))
        })?;
    let p = Arc::new(p);
    pools.insert(threads, p.clone());
    Ok(Some(p))
}

/// Run `f` without the GIL on a pool of `threads` threads, mapping errors and panics.
pub(crate) fn run<T: Send>(
    py: Python<'_>,
    threads: usize,
    f: impl FnOnce() -> core::Result<T> + Send,
) -> PyResult<T> {
    let pool = pool(threads)?;
    let out = py.allow_threads(move || {
        catch_unwind(AssertUnwindSafe(move || match pool {
            Some(p) => p.install(f),
            None => f(),
        }))
    });
    match out {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(to_py(e)),
        Err(panic) => {
            let msg = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown panic".into());
            Err(PyRuntimeError::new_err(format!(
                "sync4d rasterizer internal error (please report with the inputs that caused it): {msg}"
            )))
        }
    }
}

pub(crate) fn to_py(e: RasterError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// Number of threads rayon's global pool uses.
#[pyfunction]
pub(crate) fn default_threads() -> usize {
    rayon::current_num_threads()
}
