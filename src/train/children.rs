//! The child processes of `rfcl train`: how they are started, watched and stopped.
//!
//! * Every child runs in its own process group, so the terminal's Ctrl-C reaches only `rfcl`, which
//!   then stops the children in order (actors, learner, curriculum server: each gets SIGTERM,
//!   some seconds, then SIGKILL).
//! * Every child is started through util-linux's `setpriv --pdeathsig TERM` when it is installed:
//!   the kernel sends the child SIGTERM when `rfcl` dies, even by SIGKILL, so no child is left
//!   behind. (The death signal follows the thread that forked: children are spawned from the main
//!   thread only, which lives as long as the process.) On any error path the [`Child`]'s drop kills
//!   it too.
//! * A child's stderr, and its stdout after the ready line, go to `RUN_DIR/logs/<name>.log`; a
//!   failure shows the log's last lines.
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::{ExitStatus, Stdio};
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use rfcl_core::ready::ReadyLine;
use rfcl_proto::auth::{self, Token};
use rustix::process::{kill_process, Pid, Signal};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};

/// Lines of a child's log shown with its failure.
const LOG_TAIL_LINES: usize = 15;

/// Below this much free space a service that died is not restarted: its checkpoint, snapshot and
/// log would not fit, and it would die again for the same reason.
pub const MIN_FREE_BYTES: u64 = 32 << 20;

/// "only N MiB free on the filesystem of DIR" when `dir`'s filesystem has less than
/// [`MIN_FREE_BYTES`] available; `None` when it has enough or cannot be asked.
pub fn short_of_space(dir: &Path) -> Option<String> {
    let st = rustix::fs::statvfs(dir).ok()?;
    let free = st.f_bavail.saturating_mul(st.f_frsize);
    (free < MIN_FREE_BYTES).then(|| {
        format!(
            "only {:.1} MiB free on the filesystem of {}",
            free as f64 / f64::from(1 << 20),
            dir.display()
        )
    })
}

/// `setpriv` when it is on the PATH (util-linux; Essential on Debian).
pub fn find_setpriv() -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join("setpriv"))
        .find(|p| p.is_file())
}

/// How children are started: the program directory and the environment they share.
#[derive(Debug, Clone)]
pub struct Launcher {
    pub bin_dir: PathBuf,
    pub log_dir: PathBuf,
    pub setpriv: Option<PathBuf>,
    /// The run's token, handed to every child in its environment (never on its command line).
    pub token: Token,
}

impl Launcher {
    /// The path of a sibling binary of `rfcl`, checked.
    pub fn binary(&self, name: &str) -> Result<PathBuf> {
        let path = self.bin_dir.join(name);
        if !path.is_file() {
            bail!(
                "{} not found next to rfcl (in {}): build the workspace \
                 (`cargo build --release --workspace`)",
                name,
                self.bin_dir.display()
            );
        }
        Ok(path)
    }

    /// Starts `binary` with `args` as child `name`.
    pub fn spawn(&self, name: &str, binary: &str, args: Vec<OsString>) -> Result<Child> {
        let program = self.binary(binary)?;
        let log_path = self.log_dir.join(format!("{name}.log"));
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .with_context(|| format!("opening {}", log_path.display()))?;
        let mut cmd = match &self.setpriv {
            Some(setpriv) => {
                let mut c = tokio::process::Command::new(setpriv);
                c.args(["--pdeathsig", "TERM", "--"]).arg(&program);
                c
            }
            None => tokio::process::Command::new(&program),
        };
        cmd.args(&args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::from(log))
            .process_group(0)
            .kill_on_drop(true);
        // OpenMP's spinning barriers make libtorch several times slower on cores shared with
        // other processes (learner/src/runtime.rs).
        if std::env::var_os("OMP_WAIT_POLICY").is_none() {
            cmd.env("OMP_WAIT_POLICY", "PASSIVE");
        }
        if std::env::var_os("RUST_LOG").is_none() {
            cmd.env("RUST_LOG", "info");
        }
        // Logs are files: no terminal colour codes in them.
        cmd.env("NO_COLOR", "1");
        cmd.env(auth::TOKEN_ENV, self.token.expose())
            .env_remove(auth::TOKEN_FILE_ENV);
        let mut child = cmd
            .spawn()
            .with_context(|| format!("starting {}", program.display()))?;
        let pid = child.id().ok_or_else(|| anyhow!("{name} exited at once"))?;
        let stdout = child.stdout.take().expect("piped");
        Ok(Child {
            name: name.to_string(),
            child,
            pid,
            log_path,
            stdout: Some(stdout),
        })
    }
}

/// A running child process.
pub struct Child {
    pub name: String,
    child: tokio::process::Child,
    pub pid: u32,
    pub log_path: PathBuf,
    stdout: Option<tokio::process::ChildStdout>,
}

impl Child {
    /// Waits for the child's ready line (`<name> ready ...`) on stdout; afterwards its stdout goes
    /// to its log. An exit or `timeout` first is an error that shows the log's tail.
    pub async fn ready_line(&mut self, timeout: Duration) -> Result<ReadyLine> {
        let stdout = self.stdout.take().expect("ready_line is called once");
        let mut lines = BufReader::new(stdout).lines();
        let read = tokio::time::timeout(timeout, lines.next_line()).await;
        let line = match read {
            Ok(Ok(Some(line))) if ReadyLine::parse(&line).is_some() => ReadyLine { line },
            Ok(Ok(Some(other))) => {
                self.kill().await;
                bail!(
                    "{} printed {other:?} instead of its ready line{}",
                    self.name,
                    self.log_tail()
                )
            }
            Ok(Ok(None)) | Ok(Err(_)) => {
                let status = self.child.wait().await.ok();
                bail!(
                    "{} exited before it was ready ({}){}",
                    self.name,
                    describe(status),
                    self.log_tail()
                )
            }
            Err(_) => {
                self.kill().await;
                bail!(
                    "{} was not ready within {} s{}",
                    self.name,
                    timeout.as_secs(),
                    self.log_tail()
                )
            }
        };
        // Keep draining stdout into the log: a closed pipe would fail the child's next print.
        let log_path = self.log_path.clone();
        tokio::spawn(async move {
            let mut log = match tokio::fs::OpenOptions::new()
                .append(true)
                .open(&log_path)
                .await
            {
                Ok(f) => f,
                Err(_) => return,
            };
            while let Ok(Some(line)) = lines.next_line().await {
                let _ = log.write_all(format!("{line}\n").as_bytes()).await;
            }
        });
        Ok(line)
    }

    /// The exit status if the child has exited.
    pub fn try_wait(&mut self) -> Option<ExitStatus> {
        self.child.try_wait().ok().flatten()
    }

    /// SIGTERM, up to `grace` to exit, then SIGKILL. Returns how it ended.
    pub async fn stop(&mut self, grace: Duration) -> Option<ExitStatus> {
        if let Some(status) = self.try_wait() {
            return Some(status);
        }
        self.signal(Signal::TERM);
        match tokio::time::timeout(grace, self.child.wait()).await {
            Ok(status) => status.ok(),
            Err(_) => {
                tracing::warn!(
                    "{} did not stop within {} s of SIGTERM: SIGKILL",
                    self.name,
                    grace.as_secs()
                );
                self.kill().await
            }
        }
    }

    /// SIGKILL and reap.
    pub async fn kill(&mut self) -> Option<ExitStatus> {
        let _ = self.child.start_kill();
        self.child.wait().await.ok()
    }

    pub fn signal(&self, signal: Signal) {
        if let Some(pid) = Pid::from_raw(self.pid as i32) {
            let _ = kill_process(pid, signal);
        }
    }

    /// The last lines of the child's log, as a block to append to an error.
    pub fn log_tail(&self) -> String {
        log_tail(&self.log_path, LOG_TAIL_LINES)
    }
}

/// `"\n  <log> (last lines):\n  ..."`, or nothing when the log is empty or unreadable. Terminal
/// escape codes (colours a child wrote anyway) are taken out.
pub fn log_tail(path: &Path, lines: usize) -> String {
    let Ok(bytes) = std::fs::read(path) else {
        return String::new();
    };
    let text = String::from_utf8_lossy(&strip_ansi_escapes::strip(&bytes)).into_owned();
    let all: Vec<&str> = text.lines().collect();
    if all.is_empty() {
        return String::new();
    }
    let tail = &all[all.len().saturating_sub(lines)..];
    format!(
        "\n  {} (last lines):\n    {}",
        path.display(),
        tail.join("\n    ")
    )
}

/// "exit status 1", "killed by signal 9", ...
pub fn describe(status: Option<ExitStatus>) -> String {
    use std::os::unix::process::ExitStatusExt;
    match status {
        None => "status unknown".into(),
        Some(s) => match (s.code(), s.signal()) {
            (Some(code), _) => format!("exit status {code}"),
            (None, Some(sig)) => format!("killed by signal {sig}"),
            _ => s.to_string(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_tails_show_the_last_lines() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.log");
        assert_eq!(log_tail(&path, 3), "");
        std::fs::write(&path, "a\nb\nc\nd\n").unwrap();
        let tail = log_tail(&path, 2);
        assert!(tail.ends_with("c\n    d"), "{tail:?}");
        assert!(!tail.contains("    b"));
        std::fs::write(
            &path,
            "\x1b[2m2026-12-02T23:00:00Z\x1b[0m \x1b[31mERROR\x1b[0m learner: boom\n",
        )
        .unwrap();
        let tail = log_tail(&path, 2);
        assert!(
            tail.ends_with("2026-12-02T23:00:00Z ERROR learner: boom"),
            "{tail:?}"
        );
    }

    /// The learner (like every child) starts with `OMP_WAIT_POLICY=PASSIVE` unless the user set
    /// the variable (docs/LEARNER.md, "Threads").
    #[tokio::test]
    async fn children_get_a_passive_openmp_wait_policy() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let script = dir.path().join("fake-learner");
        std::fs::write(
            &script,
            "#!/bin/sh\necho \"fake ready omp=${OMP_WAIT_POLICY:-unset}\"\n",
        )
        .unwrap();
        std::fs::set_permissions(&script, std::fs::Permissions::from_mode(0o755)).unwrap();
        let launcher = Launcher {
            bin_dir: dir.path().to_path_buf(),
            log_dir: dir.path().to_path_buf(),
            setpriv: None,
            token: Token::parse("children-test-token-0123", "a test").unwrap(),
        };
        let mut child = launcher.spawn("learner", "fake-learner", vec![]).unwrap();
        let line = child.ready_line(Duration::from_secs(30)).await.unwrap();
        let expected = std::env::var("OMP_WAIT_POLICY").unwrap_or_else(|_| "PASSIVE".into());
        assert_eq!(line.field("omp"), Some(expected.as_str()), "{line}");
    }

    #[test]
    fn statuses_are_described() {
        use std::os::unix::process::ExitStatusExt;
        assert_eq!(
            describe(Some(ExitStatus::from_raw(1 << 8))),
            "exit status 1"
        );
        assert_eq!(
            describe(Some(ExitStatus::from_raw(9))),
            "killed by signal 9"
        );
    }
}
