//! Python inside this process (pyo3): the interpreter set up to find the venv's packages, and one
//! `rfcl_sim.bridge.Bridge` called with raw frames.
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyModule, PyTuple};

/// Overrides the site-packages directory added to `sys.path` (default: the one of the venv the
/// worker was built against, `PYO3_PYTHON`, recorded by build.rs).
pub const SITE_ENV: &str = "RFCL_PYTHON_SITE_PACKAGES";

/// The site-packages to add: `$RFCL_PYTHON_SITE_PACKAGES`, else the build's venv.
fn site_packages() -> Option<String> {
    std::env::var(SITE_ENV)
        .ok()
        .filter(|s| !s.is_empty())
        .or_else(|| option_env!("RFCL_PYTHON_SITE_PACKAGES").map(str::to_owned))
}

/// The formatted traceback of `err` (what Python would print).
pub fn traceback_text(py: Python<'_>, err: &PyErr) -> String {
    let formatted = (|| -> PyResult<String> {
        let tb = PyModule::import(py, "traceback")?;
        let lines = tb.call_method1("format_exception", (err.value(py),))?;
        let text: String = ""
            .into_pyobject(py)?
            .call_method1("join", (lines,))?
            .extract()?;
        Ok(text)
    })();
    formatted.unwrap_or_else(|_| err.to_string())
}

/// One adapter behind `Bridge.handle(op, payload) -> (status, payload)`.
pub struct Bridge {
    bridge: Py<PyAny>,
}

impl Bridge {
    /// Initialises Python (once per process), puts the venv's site-packages on `sys.path` (an
    /// embedded interpreter does not know it runs for a venv) and makes the
    /// adapter. The error is the Python traceback, or for bad input (an `AdapterError`, whose
    /// message names what was wrong and what was expected) that message alone.
    pub fn new(suite: &str, env_id: &str, options_json: &str) -> Result<Self, String> {
        Python::attach(|py| {
            let make = || -> PyResult<Py<PyAny>> {
                if let Some(site) = site_packages() {
                    PyModule::import(py, "site")?.call_method1("addsitedir", (site,))?;
                }
                let module = PyModule::import(py, "rfcl_sim.bridge")?;
                let bridge = module
                    .getattr("Bridge")?
                    .call1((suite, env_id, options_json))?;
                Ok(bridge.unbind())
            };
            make().map(|bridge| Bridge { bridge }).map_err(|e| {
                let bad_input = e
                    .get_type(py)
                    .name()
                    .is_ok_and(|name| name == "AdapterError");
                if bad_input {
                    e.value(py).to_string()
                } else {
                    traceback_text(py, &e)
                }
            })
        })
    }

    /// The answer to one request: `(status, payload)`. A failure of the call itself (not one the
    /// bridge caught) is reported as an exception status with its traceback.
    pub fn handle(&self, op: u8, payload: &[u8]) -> (u8, Vec<u8>) {
        Python::attach(|py| {
            let call = || -> PyResult<(u8, Vec<u8>)> {
                let answer = self
                    .bridge
                    .bind(py)
                    .call_method1("handle", (op, PyBytes::new(py, payload)))?;
                let answer = answer.cast_into::<PyTuple>()?;
                let status: u8 = answer.get_item(0)?.extract()?;
                let bytes = answer.get_item(1)?;
                let bytes = bytes.cast::<PyBytes>()?;
                Ok((status, bytes.as_bytes().to_vec()))
            };
            call().unwrap_or_else(|e| {
                (
                    rfcl_actor::python::protocol::STATUS_EXCEPTION,
                    traceback_text(py, &e).into_bytes(),
                )
            })
        })
    }

    /// Runs `n` steps of uniform actions straight on the adapter, timed inside Python: the raw
    /// simulator rate (the bench's baseline). Returns steps per second.
    pub fn raw_steps_per_s(&self, n: u32) -> Result<f64, String> {
        Python::attach(|py| {
            let code = c"
import time, numpy as np
def raw(adapter, n):
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1, 1, (n, adapter.action_dim)).astype(np.float32)
    adapter.reset(0, {})
    t = time.perf_counter()
    for a in acts:
        adapter.step(a)
    return n / (time.perf_counter() - t)
";
            let run = || -> PyResult<f64> {
                let m = PyModule::from_code(py, code, c"rfcl_bench_raw.py", c"rfcl_bench_raw")?;
                let adapter = self.bridge.bind(py).getattr("adapter")?;
                m.getattr("raw")?.call1((adapter, n))?.extract()
            };
            run().map_err(|e| traceback_text(py, &e))
        })
    }
}
