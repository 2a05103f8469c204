//! rfcl's cross-process test helpers: the one home of what the tests of every crate need to run
//! the service binaries as children. It is a dev-dependency only (tests/crate_graph.rs checks
//! that), and depends on no service crate: services meet over the wire, and so do their tests.
//!
//! * [`child`]: a child process killed and reaped when dropped ([`child::ChildGuard`]), its stderr
//!   kept for failure messages, and a service's ready line (`<name> ready grpc=ADDR ...`) waited
//!   for with a timeout and parsed ([`child::ReadyLine`]);
//! * [`binaries`]: the service binaries next to the test executable, built with cargo (same
//!   profile) when one is missing;
//! * [`hdf5`]: the lock that keeps forks away from open HDF5 files;
//! * [`demos`]: small synthetic demo files whose states say which demo and step they are;
//! * [`browser`]: headless Chromium for the dashboard's pages;
//! * [`assert_contains_all`]: a command's report checked for the lines it must hold.
pub mod binaries;
pub mod browser;
pub mod child;
pub mod demos;
pub mod hdf5;

/// Panics naming the first of `needles` that `text` lacks, and showing `text`.
#[track_caller]
pub fn assert_contains_all(text: &str, needles: &[&str]) {
    if let Some(missing) = needles.iter().find(|n| !text.contains(*n)) {
        panic!("{missing:?} missing from:\n{text}");
    }
}
