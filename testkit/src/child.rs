//! Child processes for cross-process tests.
//!
//! A test that starts a service must never leave it running, whatever assertion fails first:
//! [`ChildGuard`] kills and reaps its child when dropped (or, with
//! [`ChildGuard::terminate_on_drop`], asks it to stop with SIGTERM first). It drains the child's
//! stderr into memory, so the child never blocks on a full pipe and a failure can show what the
//! child said ([`ChildGuard::stderr_text`], [`ChildGuard::stderr_tail`]); `RFCL_TEST_LOGS=1`
//! also echoes it, line by line, to the test's stderr.
//!
//! The services announce that they serve with one line on stdout,
//! `curriculum-server ready grpc=ADDR dashboard=http://ADDR/` or
//! `learner ready grpc=ADDR [metrics=URL]`: [`start_service`] spawns one, waits for that line with
//! a timeout and parses it into a [`ReadyLine`]; an exit or a timeout first panics with the
//! child's exit status and the tail of its stderr. (The launcher reads the same lines in
//! src/train/children.rs, its own production code.)
//!
//! Every spawn here holds the HDF5 fork lock ([`crate::hdf5`]).
use std::io::{BufRead, BufReader};
use std::ops::{Deref, DerefMut};
use std::process::{Child, Command, ExitStatus, Output, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

pub use rfcl_core::ready::ReadyLine;
pub use rustix::process::Signal;

/// How long [`start_service`] waits for a ready line: services start in a second or two, but a
/// loaded 2-core machine running tests in parallel can take much longer (libtorch's start-up).
pub const READY_TIMEOUT: Duration = Duration::from_secs(120);

/// How many lines of stderr failure messages show.
const TAIL_LINES: usize = 40;

/// `cmd.spawn()` under the HDF5 fork lock.
pub fn spawn_locked(cmd: &mut Command) -> std::io::Result<Child> {
    let _guard = crate::hdf5::fork_guard();
    cmd.spawn()
}

/// Runs `cmd` to completion like [`Command::output`] (stdin empty, stdout and stderr captured),
/// spawned under the HDF5 fork lock.
pub fn output(cmd: &mut Command) -> Output {
    let child = spawn_locked(
        cmd.stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped()),
    )
    .unwrap_or_else(|e| panic!("starting {}: {e}", program(cmd)));
    child
        .wait_with_output()
        .unwrap_or_else(|e| panic!("waiting for {}: {e}", program(cmd)))
}

/// Runs `cmd` to completion like [`output`] and returns its stdout; panics with the command and
/// its stderr when it fails.
pub fn succeed(cmd: &mut Command) -> String {
    let out = output(cmd);
    assert!(
        out.status.success(),
        "{} failed ({}):\n{}",
        program(cmd),
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Runs `cmd` to completion like [`output`]: whether it succeeded, and its stdout followed by its
/// stderr (a command's report and its messages, as a user sees them).
pub fn outcome(cmd: &mut Command) -> (bool, String) {
    let out = output(cmd);
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    (
        out.status.success(),
        text + &String::from_utf8_lossy(&out.stderr),
    )
}

/// Sets the run token of a test's services: `RFCL_TOKEN=token`, and no `RFCL_TOKEN_FILE` from the
/// test's own environment.
pub fn with_token<'a>(cmd: &'a mut Command, token: &str) -> &'a mut Command {
    cmd.env("RFCL_TOKEN", token).env_remove("RFCL_TOKEN_FILE")
}

/// Spawns the service `cmd` with stdout piped and waits up to [`READY_TIMEOUT`] for its ready
/// line. `name` names it in failure messages.
pub fn start_service(name: &str, cmd: &mut Command) -> (ChildGuard, ReadyLine) {
    let mut child = ChildGuard::spawn(name, cmd.stdout(Stdio::piped()));
    let ready = child.wait_ready(READY_TIMEOUT);
    (child, ready)
}

/// Sends `signal` to process `pid` (nothing when it is gone).
pub fn signal(pid: u32, signal: Signal) {
    if let Some(pid) = rustix::process::Pid::from_raw(pid as i32) {
        let _ = rustix::process::kill_process(pid, signal);
    }
}

/// What dropping a [`ChildGuard`] does to a child still running.
#[derive(Clone, Copy, Debug)]
enum OnDrop {
    Kill,
    /// SIGTERM, then SIGKILL after the grace period.
    Terminate(Duration),
}

/// A child process that is killed (and reaped) when dropped; its stderr is kept, and its stdout
/// lines when stdout is piped. Derefs to the [`Child`].
pub struct ChildGuard {
    name: String,
    child: Child,
    on_drop: OnDrop,
    stderr: Arc<Mutex<String>>,
    stderr_drain: Option<JoinHandle<()>>,
    stdout: Arc<Mutex<Vec<String>>>,
    stdout_lines: Option<Receiver<String>>,
}

impl ChildGuard {
    /// Spawns `cmd` (under the HDF5 fork lock) with its stderr piped and kept; stdout is as `cmd`
    /// sets it. Panics when it cannot start.
    pub fn spawn(name: &str, cmd: &mut Command) -> ChildGuard {
        let child = spawn_locked(cmd.stderr(Stdio::piped()))
            .unwrap_or_else(|e| panic!("starting {name} ({}): {e}", program(cmd)));
        ChildGuard::new(name, child)
    }

    /// Guards a child spawned by the caller (with [`spawn_locked`]); its stderr and stdout are
    /// kept when they are pipes.
    pub fn new(name: &str, mut child: Child) -> ChildGuard {
        let stderr = Arc::new(Mutex::new(String::new()));
        let stderr_drain = child.stderr.take().map(|pipe| {
            let keep = stderr.clone();
            let prefix = name.to_string();
            std::thread::spawn(move || {
                let show = std::env::var_os("RFCL_TEST_LOGS").is_some();
                for line in BufReader::new(pipe).lines() {
                    let Ok(line) = line else { break };
                    if show {
                        eprintln!("{prefix}: {line}");
                    }
                    let mut all = keep.lock().unwrap_or_else(|p| p.into_inner());
                    all.push_str(&line);
                    all.push('\n');
                }
            })
        });
        let stdout = Arc::new(Mutex::new(Vec::new()));
        // Kept draining after the ready line: a closed pipe would fail the child's next print.
        let stdout_lines = child.stdout.take().map(|pipe| {
            let (send, receive) = std::sync::mpsc::channel();
            let keep = stdout.clone();
            std::thread::spawn(move || {
                for line in BufReader::new(pipe).lines() {
                    let Ok(line) = line else { break };
                    keep.lock()
                        .unwrap_or_else(|p| p.into_inner())
                        .push(line.clone());
                    let _ = send.send(line);
                }
            });
            receive
        });
        ChildGuard {
            name: name.to_string(),
            child,
            on_drop: OnDrop::Kill,
            stderr,
            stderr_drain,
            stdout,
            stdout_lines,
        }
    }

    /// On drop, SIGTERM a child still running and give it `grace` to exit before SIGKILL (for a
    /// child that must stop its own children, like `rfcl train`).
    pub fn terminate_on_drop(mut self, grace: Duration) -> ChildGuard {
        self.on_drop = OnDrop::Terminate(grace);
        self
    }

    /// The name failure messages use.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Waits up to `timeout` for the first stdout line, which must be the child's ready line
    /// (`<name> ready key=value ...`). Panics with the child's exit status and stderr tail when it
    /// exits or prints something else first, or when the time runs out (the child is killed
    /// then). Stdout must be piped; call once.
    pub fn wait_ready(&mut self, timeout: Duration) -> ReadyLine {
        let lines = self
            .stdout_lines
            .take()
            .expect("wait_ready needs the child's stdout piped, and is called once");
        match lines.recv_timeout(timeout) {
            Ok(line) if ReadyLine::parse(&line).is_some() => ReadyLine { line },
            Ok(line) => {
                self.kill_and_reap();
                self.fail(format!("printed {line:?} instead of its ready line"))
            }
            Err(RecvTimeoutError::Disconnected) => {
                let status = match self.exit_status_within(Duration::from_secs(10)) {
                    Some(status) => status.to_string(),
                    None => "still running after closing stdout".into(),
                };
                self.fail(format!("exited before it was ready ({status})"))
            }
            Err(RecvTimeoutError::Timeout) => {
                self.kill_and_reap();
                self.fail(format!("was not ready within {timeout:?}"))
            }
        }
    }

    /// The stdout lines read so far (stdout piped).
    pub fn stdout_lines(&self) -> Vec<String> {
        self.stdout
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// The child's stderr so far; all of it once the child has exited.
    pub fn stderr_text(&mut self) -> String {
        if matches!(self.child.try_wait(), Ok(Some(_))) {
            self.finish_stderr();
        }
        self.stderr
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// The last `n` lines of stderr, as a message suffix (`"; its stderr ends:\n..."`), or
    /// `"; no stderr"`.
    pub fn stderr_tail(&mut self, n: usize) -> String {
        let text = self.stderr_text();
        let lines: Vec<&str> = text.lines().collect();
        if lines.is_empty() {
            return "; no stderr".into();
        }
        let tail = lines[lines.len().saturating_sub(n)..].join("\n");
        format!("; its stderr ends:\n{tail}")
    }

    /// Sends `sig` to the child.
    pub fn signal(&self, sig: Signal) {
        signal(self.child.id(), sig);
    }

    /// SIGKILL and reap.
    pub fn sigkill(&mut self) {
        self.child.kill().expect("SIGKILL to the child");
        self.child.wait().expect("reaping the child");
    }

    /// SIGTERM, then waits up to `limit` for the exit (panics with the stderr tail after it).
    pub fn sigterm(&mut self, limit: Duration) -> ExitStatus {
        self.signal(Signal::TERM);
        self.wait_within(limit)
    }

    /// Waits up to `limit` for the child to exit on its own; panics with its stderr tail after.
    pub fn wait_within(&mut self, limit: Duration) -> ExitStatus {
        match self.exit_status_within(limit) {
            Some(status) => status,
            None => self.fail(format!("did not exit within {limit:?}")),
        }
    }

    /// The exit status once the child exits within `limit`; `None` when it is still running.
    pub fn exit_status_within(&mut self, limit: Duration) -> Option<ExitStatus> {
        let until = Instant::now() + limit;
        loop {
            if let Some(status) = self.child.try_wait().expect("polling the child") {
                return Some(status);
            }
            if Instant::now() >= until {
                return None;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Panics with `<name> <what>` and the tail of the child's stderr.
    fn fail(&mut self, what: String) -> ! {
        let tail = self.stderr_tail(TAIL_LINES);
        panic!("{} {what}{tail}", self.name)
    }

    fn kill_and_reap(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Joins the stderr drain once it has read the pipe's end. A grandchild that inherited the
    /// pipe can keep it open past the child's exit: then this gives up after a moment.
    fn finish_stderr(&mut self) {
        let until = Instant::now() + Duration::from_secs(2);
        while let Some(drain) = &self.stderr_drain {
            if drain.is_finished() {
                let _ = self.stderr_drain.take().unwrap().join();
            } else if Instant::now() >= until {
                break;
            } else {
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }
}

impl Deref for ChildGuard {
    type Target = Child;
    fn deref(&self) -> &Child {
        &self.child
    }
}

impl DerefMut for ChildGuard {
    fn deref_mut(&mut self) -> &mut Child {
        &mut self.child
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        if let OnDrop::Terminate(grace) = self.on_drop {
            if matches!(self.child.try_wait(), Ok(None)) {
                self.signal(Signal::TERM);
                let _ = self.exit_status_within(grace);
            }
        }
        self.kill_and_reap();
    }
}

fn program(cmd: &Command) -> String {
    cmd.get_program().to_string_lossy().into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_service_that_exits_first_panics_with_its_stderr() {
        let result = std::panic::catch_unwind(|| {
            start_service(
                "sh",
                Command::new("sh").args(["-c", "echo oops >&2; exit 3"]),
            )
        });
        let message = *result.err().unwrap().downcast::<String>().unwrap();
        assert!(
            message.contains("sh exited before it was ready"),
            "{message}"
        );
        assert!(message.contains("exit status: 3"), "{message}");
        assert!(message.contains("oops"), "{message}");
    }

    #[test]
    fn a_ready_service_is_parsed_and_killed_on_drop() {
        let (child, ready) = start_service(
            "sh",
            Command::new("sh").args(["-c", "echo 'fake ready grpc=1.2.3.4:5'; exec sleep 600"]),
        );
        assert_eq!(
            ready.grpc_url().expect("a grpc= address on the ready line"),
            "http://1.2.3.4:5"
        );
        let pid = child.id();
        drop(child);
        assert!(!std::path::Path::new(&format!("/proc/{pid}")).exists());
    }

    #[test]
    fn a_slow_service_times_out_and_is_killed() {
        let mut child = ChildGuard::spawn(
            "sleeper",
            Command::new("sh")
                .args(["-c", "echo starting >&2; exec sleep 600"])
                .stdout(Stdio::piped()),
        );
        let pid = child.id();
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            child.wait_ready(Duration::from_millis(300))
        }));
        let message = *result.err().unwrap().downcast::<String>().unwrap();
        assert!(
            message.contains("sleeper was not ready within"),
            "{message}"
        );
        assert!(message.contains("starting"), "{message}");
        assert!(!std::path::Path::new(&format!("/proc/{pid}")).exists());
    }
}
