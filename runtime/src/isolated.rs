//! Reading a file with a library that may crash the process instead of returning an error
//! (libhdf5 segfaults on some damaged files; fuzzing the demo reader found them). A service reads
//! such a file once in a child copy of itself first, so a damaged file ends the service with an
//! error naming it instead of a bare segmentation fault that a container engine restarts forever.
//!
//! The child is this same binary with [`CHILD_ENV`] set: `main()` calls [`serve_if_child`] first
//! thing, which reads the file and exits.
use std::os::unix::process::ExitStatusExt;
use std::path::Path;
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

/// Set in the child's environment to the file it is to read.
pub const CHILD_ENV: &str = "RFCL_ISOLATED_READ";

/// In the child of [`refuse_if_it_crashes`]: runs `read` on the file named by [`CHILD_ENV`] and
/// exits (0 when it read the file, 1 when it refused it cleanly). Elsewhere it returns at once.
pub fn serve_if_child(read: impl FnOnce(&Path) -> Result<()>) {
    if let Some(file) = std::env::var_os(CHILD_ENV) {
        let code = match read(Path::new(&file)) {
            Ok(()) => 0,
            Err(_) => 1,
        };
        std::process::exit(code);
    }
}

/// Reads `file` in a child copy of this binary (whose `main()` calls [`serve_if_child`]) and fails,
/// naming the file and `library`, only when the read crashed the child. A file the reader refuses
/// cleanly passes: the caller reads it again and reports that with its own context.
pub fn refuse_if_it_crashes(file: &Path, library: &str) -> Result<()> {
    let exe = std::env::current_exe().context("locating this binary to read a file in a child")?;
    let status = Command::new(exe)
        .env(CHILD_ENV, file)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .with_context(|| format!("reading {} in a child process", file.display()))?;
    if let Some(signal) = status.signal() {
        bail!(
            "{}: reading it crashed the {library} library (signal {signal}): the file is damaged; \
             make it again or restore it",
            file.display()
        );
    }
    Ok(())
}
