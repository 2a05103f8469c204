//! The HDF5 fork lock.
//!
//! libhdf5 opens files without `O_CLOEXEC` and holds a `flock` on each open file: a child forked
//! while another test thread of the same process has a demo file open inherits that descriptor,
//! and with it the lock, for its whole life (a server started then cannot open the file, or a
//! later writer blocks). Tests run on many threads, so every place that writes or reads an HDF5
//! file in the test process, and every spawn of a child, holds this one lock: no fork happens while
//! an HDF5 file is open here. [`crate::child`] and [`crate::demos`] take it themselves.
use std::sync::{Mutex, MutexGuard};

static FORK_LOCK: Mutex<()> = Mutex::new(());

/// Holds the fork lock until dropped: take it around HDF5 file access and around spawning
/// children (a poisoned lock is taken anyway: a failed test must not fail the others).
pub fn fork_guard() -> MutexGuard<'static, ()> {
    FORK_LOCK.lock().unwrap_or_else(|p| p.into_inner())
}
