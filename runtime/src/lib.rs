//! One home for a service binary's `main()` (`curriculum-server`, `learner`, `actor`): logs to
//! stderr, the tokio runtime, SIGINT/SIGTERM, and the way a failure ends the process (one line
//! `error: …` with the whole cause chain on stderr, exit status 1).
//!
//! ```no_run
//! use rfcl_runtime::Flavor;
//!
//! fn main() -> std::process::ExitCode {
//!     rfcl_runtime::init_logging();
//!     rfcl_runtime::run(Flavor::CurrentThread, async {
//!         rfcl_runtime::shutdown_signal().await;
//!         Ok(())
//!     })
//! }
//! ```
//!
//! [`tasks`]: a service's named tasks under one supervisor.
//!
//! Depends on no workspace crate (tests/crate_graph.rs).
#![forbid(unsafe_code)]

pub mod isolated;
pub mod tasks;

use std::future::Future;
use std::process::ExitCode;

use anyhow::{Context, Result};
use tokio::signal::unix::{signal, Signal, SignalKind};

/// Logs (`tracing`) to stderr, filtered by `RUST_LOG` (default `info`). Stdout stays free for the
/// services' one machine-readable ready line.
pub fn init_logging() {
    init_logging_or("info");
}

/// [`init_logging`] with another filter when `RUST_LOG` is unset or invalid.
pub fn init_logging_or(default_filter: &str) {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| default_filter.into()),
        )
        .with_writer(std::io::stderr)
        .init();
}

/// Which tokio runtime a service runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Flavor {
    /// Worker threads on every core (tokio's default).
    MultiThread,
    /// This many worker threads.
    Workers(usize),
    /// Everything on the main thread.
    CurrentThread,
}

impl Flavor {
    fn build(self) -> std::io::Result<tokio::runtime::Runtime> {
        let mut builder = match self {
            Flavor::MultiThread => tokio::runtime::Builder::new_multi_thread(),
            Flavor::Workers(n) => {
                let mut b = tokio::runtime::Builder::new_multi_thread();
                b.worker_threads(n.max(1));
                b
            }
            Flavor::CurrentThread => tokio::runtime::Builder::new_current_thread(),
        };
        builder.enable_all().build()
    }
}

/// Runs `main` on a runtime of `flavor` and turns its outcome into the exit status: success, or
/// [`fail`] (a service that names itself in its errors adds that as the outermost context, e.g.
/// `.with_context(|| format!("actor {id}"))`, printed `error: actor 3: …`).
pub fn run(flavor: Flavor, main: impl Future<Output = Result<()>>) -> ExitCode {
    let runtime = match flavor.build() {
        Ok(r) => r,
        Err(e) => return fail(anyhow::Error::new(e).context("starting the async runtime")),
    };
    match runtime.block_on(main) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => fail(err),
    }
}

/// Prints `error: ` and the error with its causes, each once, on one line (`{:#}`) to stderr, and
/// returns the failure exit status.
pub fn fail(err: impl Into<anyhow::Error>) -> ExitCode {
    eprintln!("error: {:#}", err.into());
    ExitCode::FAILURE
}

/// Resolves on SIGINT or SIGTERM (SIGTERM only where SIGINT was ignored when the process
/// started, see [`Signals`]). Where no SIGTERM handler can be installed it says so and waits for
/// SIGINT only.
pub async fn shutdown_signal() {
    match Signals::install() {
        Ok(mut signals) => signals.recv().await,
        Err(e) => {
            tracing::warn!("no SIGTERM handler ({e:#}); stopping on SIGINT only");
            let _ = tokio::signal::ctrl_c().await;
        }
    }
}

/// SIGINT and SIGTERM, installed once and received as often as they come (a first signal to
/// finish cleanly, a second to abort). Install it first thing, so that a signal during start-up
/// is handled rather than fatal.
///
/// The Unix convention holds: a process whose parent left SIGINT ignored (a background job of a
/// shell script, `nohup`) keeps ignoring it for its whole life, so that an interrupt behaves the
/// same whenever it comes, and its children inherit that; SIGTERM always stops it cleanly.
/// Without this, SIGINT was ignored until the handler replaced the inherited disposition and
/// honoured after, and a run's fate depended on when the interrupt came.
#[derive(Debug)]
pub struct Signals {
    /// `None` where SIGINT was ignored at start-up.
    interrupt: Option<Signal>,
    terminate: Signal,
}

impl Signals {
    /// Must be called within a tokio runtime.
    pub fn install() -> Result<Self> {
        let interrupt = if sigint_ignored() {
            tracing::info!("SIGINT is ignored (the parent's choice): stopping on SIGTERM only");
            None
        } else {
            Some(signal(SignalKind::interrupt()).context("installing the SIGINT handler")?)
        };
        Ok(Self {
            interrupt,
            terminate: signal(SignalKind::terminate()).context("installing the SIGTERM handler")?,
        })
    }

    /// The next SIGINT or SIGTERM.
    pub async fn recv(&mut self) {
        match &mut self.interrupt {
            Some(interrupt) => tokio::select! {
                _ = interrupt.recv() => {}
                _ = self.terminate.recv() => {}
            },
            None => {
                self.terminate.recv().await;
            }
        }
    }
}

/// Whether SIGINT's disposition is "ignore", from the kernel's `SigIgn` mask of the process
/// (`/proc/self/status`). Asked before any handler of ours replaces it; false where it cannot be
/// read.
fn sigint_ignored() -> bool {
    std::fs::read_to_string("/proc/self/status").is_ok_and(|status| sigint_in_ignored_mask(&status))
}

/// Whether the `SigIgn:` line of a `/proc/<pid>/status` text has SIGINT's bit (signal 2: bit 1).
fn sigint_in_ignored_mask(status: &str) -> bool {
    status
        .lines()
        .find_map(|line| line.strip_prefix("SigIgn:"))
        .and_then(|mask| u64::from_str_radix(mask.trim(), 16).ok())
        .is_some_and(|mask| mask & (1 << 1) != 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_flavor_runs_a_future_to_its_exit_status() {
        for flavor in [
            Flavor::MultiThread,
            Flavor::Workers(1),
            Flavor::CurrentThread,
        ] {
            assert_eq!(run(flavor, async { Ok(()) }), ExitCode::SUCCESS);
            assert_eq!(
                run(flavor, async { Err(anyhow::anyhow!("no")) }),
                ExitCode::FAILURE
            );
        }
    }

    #[test]
    fn signals_install_inside_a_runtime() {
        let rt = Flavor::CurrentThread.build().unwrap();
        rt.block_on(async { Signals::install().unwrap() });
    }

    /// SIGINT is signal 2, bit 1 of the kernel's mask: `0000000000000002` and `0000000001001006`
    /// have it, `0000000000001000` (SIGPIPE, signal 13, alone) does not.
    #[test]
    fn sigint_is_read_from_the_ignored_mask() {
        let status =
            |mask: &str| format!("Name:\trfcl\nSigBlk:\t0000000000000000\nSigIgn:\t{mask}\n");
        assert!(sigint_in_ignored_mask(&status("0000000000000002")));
        assert!(sigint_in_ignored_mask(&status("0000000001001006")));
        assert!(!sigint_in_ignored_mask(&status("0000000000001000")));
        assert!(!sigint_in_ignored_mask("Name:\trfcl\n"));
    }
}
