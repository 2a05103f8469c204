//! libhdf5 crashes on some damaged files (a segmentation fault inside the library, found by
//! fuzzing the demo reader) instead of returning an error. `rfcl` therefore reads a user's demo
//! file first in a child process of its own: a damaged file is then reported by name, instead of
//! killing `rfcl demos inspect` without a word or a service at start-up.

use std::os::unix::process::ExitStatusExt;
use std::path::Path;
use std::process::{Command, ExitStatus, Stdio};

use anyhow::{bail, Context, Result};

use super::ReplayArgs;

/// The hidden subcommand that reads a demo file in this process (`rfcl demos load FILE`).
pub const LOAD: [&str; 2] = ["demos", "load"];

/// Reads `file` in a child process and fails, naming the file, only when reading it crashes the
/// reader: a file the reader refuses cleanly is left to the services, which report it with their
/// own context.
pub fn refuse_if_it_crashes_the_reader(file: &Path) -> Result<()> {
    let status = child(file, &ReplayArgs::default())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .with_context(|| format!("reading demo file {} in a child process", file.display()))?;
    crashed(file, status)
}

/// `rfcl demos inspect`: the child prints the summary; a crash becomes an error naming the file.
pub fn inspect(file: &Path, replay: &ReplayArgs) -> Result<ExitStatus> {
    let status = child(file, replay)
        .status()
        .with_context(|| format!("reading demo file {} in a child process", file.display()))?;
    crashed(file, status)?;
    Ok(status)
}

fn child(file: &Path, replay: &ReplayArgs) -> Command {
    let exe = std::env::current_exe().unwrap_or_else(|_| "rfcl".into());
    let mut cmd = Command::new(exe);
    cmd.args(LOAD).arg(file);
    if replay.replay {
        cmd.arg("--replay");
    }
    if let Some(config) = &replay.config {
        cmd.arg("--config").arg(config);
    }
    cmd
}

fn crashed(file: &Path, status: ExitStatus) -> Result<()> {
    if let Some(signal) = status.signal() {
        bail!(
            "{}: reading it crashed the HDF5 library (signal {signal}): the file is damaged; \
             make the demos again or restore the file",
            file.display()
        );
    }
    Ok(())
}
