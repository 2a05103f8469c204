//! The Python interpreter rfcl's tools run under (demo generation, conversion and recording): the
//! venv's, which holds the simulators, unless the user names another.
use std::path::PathBuf;

/// Overrides the Python interpreter (default: the one rfcl was built with, `PYO3_PYTHON`).
pub const PYTHON_ENV: &str = "RFCL_PYTHON";

/// `$RFCL_PYTHON`, else the venv Python rfcl was built with (`PYO3_PYTHON`), else `python3`.
pub fn python_program() -> PathBuf {
    if let Some(p) = std::env::var_os(PYTHON_ENV).filter(|p| !p.is_empty()) {
        return PathBuf::from(p);
    }
    option_env!("PYO3_PYTHON")
        .map(PathBuf::from)
        .filter(|p| p.is_file())
        .unwrap_or_else(|| PathBuf::from("python3"))
}
