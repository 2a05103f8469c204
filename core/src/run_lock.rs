//! One owner per run directory and role: the launcher (`rfcl train`), the learner and the
//! curriculum server each hold an exclusive lock on `RUN_DIR/<role>.lock` for as long as they run,
//! so that a second one started on the same directory (a second `--resume` in another terminal, a
//! service started by hand beside a running one, a compose restart on a shared volume) is refused
//! before it writes anything, instead of two writers interleaving checkpoints and summaries.
//!
//! The lock is the kernel's (`flock`), taken on an open file: it goes when its process ends, however
//! it ends (`kill -9` included), so there is never a stale lock to remove by hand. The file holds the
//! holder's pid, which the refusal names. (On network filesystems without `flock` the lock is a
//! no-op or an error, as the filesystem decides.)
use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use thiserror::Error;

#[derive(Debug, Error)]
pub enum RunLockError {
    #[error(
        "{dir} is in use by another {role} ({holder}; lock file {file}): stop it first, or choose \
         another run directory",
        dir = .dir.display(),
        file = .file.display()
    )]
    Held {
        dir: PathBuf,
        role: String,
        holder: String,
        file: PathBuf,
    },
    #[error("locking {}", .file.display())]
    Io {
        file: PathBuf,
        source: std::io::Error,
    },
}

/// Held while alive; dropping it (or the process ending) releases the directory.
#[derive(Debug)]
pub struct RunDirLock {
    _file: File,
}

impl RunDirLock {
    /// Takes `run_dir/<role>.lock` (the directory must exist), or says who holds it.
    pub fn acquire(run_dir: &Path, role: &str) -> Result<Self, RunLockError> {
        let path = run_dir.join(format!("{role}.lock"));
        let io = |source| RunLockError::Io {
            file: path.clone(),
            source,
        };
        // Not truncated on open: the holder's pid must survive a refused attempt.
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(io)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                let mut holder = String::new();
                let _ = file.read_to_string(&mut holder);
                let holder = match holder.trim() {
                    "" => "pid unknown".to_string(),
                    pid => format!("pid {pid}"),
                };
                return Err(RunLockError::Held {
                    dir: run_dir.to_path_buf(),
                    role: role.to_string(),
                    holder,
                    file: path,
                });
            }
            Err(TryLockError::Error(e)) => return Err(io(e)),
        }
        file.set_len(0).map_err(io)?;
        file.seek(SeekFrom::Start(0)).map_err(io)?;
        writeln!(file, "{}", std::process::id()).map_err(io)?;
        Ok(Self { _file: file })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_holder_is_refused_with_the_first_ones_pid_until_it_lets_go() {
        let dir = tempfile::tempdir().unwrap();
        let first = RunDirLock::acquire(dir.path(), "learner").unwrap();
        let refused = RunDirLock::acquire(dir.path(), "learner").unwrap_err();
        let text = refused.to_string();
        assert!(
            text.contains("in use by another learner")
                && text.contains(&format!("pid {}", std::process::id()))
                && text.contains("learner.lock"),
            "{text}"
        );
        // Another role on the same directory is independent.
        let _server = RunDirLock::acquire(dir.path(), "curriculum-server").unwrap();
        drop(first);
        RunDirLock::acquire(dir.path(), "learner").unwrap();
    }
}
