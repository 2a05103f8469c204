//! One `rfcl-sim-worker` child process: spawned with piped stdin/stdout/stderr; every answer is
//! awaited with `poll` and a deadline (a hung simulator is detected, not waited on forever), in
//! the calling thread (a reader thread would add a thread wake-up to every step); the tail of its
//! stderr is kept for the report when it dies.
use std::collections::VecDeque;
use std::io::{BufRead, BufReader, BufWriter};
use std::path::Path;
use std::process::{Child, ChildStdin, ChildStdout, Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::protocol::{read_frame, write_frame, Frame};

/// Lines of the worker's stderr kept for crash reports.
const STDERR_TAIL: usize = 30;

/// Why a call got no answer.
#[derive(Debug)]
pub enum Failure {
    /// The worker closed its pipes or could not be written to: it died (or is dying).
    Died,
    /// No answer within the deadline; the worker has been killed.
    TimedOut(Duration),
    /// The worker sent something that is not a frame; it has been killed.
    Corrupt(String),
}

pub struct WorkerProcess {
    child: Child,
    stdin: Option<BufWriter<ChildStdin>>,
    stdout: BufReader<ChildStdout>,
    stderr_tail: Arc<Mutex<VecDeque<String>>>,
    stderr_thread: Option<JoinHandle<()>>,
}

impl WorkerProcess {
    /// Starts `program` with `args`; `label` names it in the forwarded log lines.
    pub fn spawn(program: &Path, args: &[String], label: String) -> std::io::Result<Self> {
        let mut child = Command::new(program)
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()?;
        let stdout = child.stdout.take().expect("piped");
        let stderr = child.stderr.take().expect("piped");
        let stdin = child.stdin.take().map(BufWriter::new);
        let stderr_tail = Arc::new(Mutex::new(VecDeque::with_capacity(STDERR_TAIL)));
        let tail = stderr_tail.clone();
        let stderr_thread = std::thread::Builder::new()
            .name(format!("{label}-err"))
            .spawn(move || {
                for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                    tracing::debug!(target: "rfcl_sim_worker", worker = %label, "{line}");
                    let mut t = tail.lock().unwrap_or_else(|p| p.into_inner());
                    if t.len() == STDERR_TAIL {
                        t.pop_front();
                    }
                    t.push_back(line);
                }
            })?;
        Ok(WorkerProcess {
            child,
            stdin,
            stdout: BufReader::new(stdout),
            stderr_tail,
            stderr_thread: Some(stderr_thread),
        })
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Sends a request (unless `request` is `None`: the start-up hello) and waits for the answer.
    pub fn call(
        &mut self,
        request: Option<(u8, &[u8])>,
        deadline: Duration,
    ) -> Result<Frame, Failure> {
        if let Some((op, payload)) = request {
            let stdin = self.stdin.as_mut().ok_or(Failure::Died)?;
            if write_frame(stdin, op, payload).is_err() {
                return Err(Failure::Died);
            }
        }
        if self.stdout.buffer().is_empty() && !self.readable_within(deadline) {
            self.kill();
            return Err(Failure::TimedOut(deadline));
        }
        match read_frame(&mut self.stdout) {
            Ok(Some(frame)) => Ok(frame),
            Ok(None) => Err(Failure::Died),
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => Err(Failure::Died),
            Err(e) => {
                self.kill();
                Err(Failure::Corrupt(e.to_string()))
            }
        }
    }

    /// Whether the worker's stdout has data (or reached its end) within `deadline`.
    fn readable_within(&self, deadline: Duration) -> bool {
        use rustix::event::{poll, PollFd, PollFlags, Timespec};
        let until = Instant::now() + deadline;
        loop {
            let left = until.saturating_duration_since(Instant::now());
            let timeout = Timespec {
                tv_sec: left.as_secs() as _,
                tv_nsec: left.subsec_nanos() as _,
            };
            let mut fds = [PollFd::new(self.stdout.get_ref(), PollFlags::IN)];
            match poll(&mut fds, Some(&timeout)) {
                Ok(0) if left.is_zero() => return false,
                Ok(0) | Err(rustix::io::Errno::INTR) => continue,
                // Readable, or hung up / in error: the read that follows tells which.
                Ok(_) | Err(_) => return true,
            }
        }
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
    }

    /// Once the worker is dead or dying: its exit status (killing it if it has not exited within
    /// a few seconds) and the last lines of its stderr.
    pub fn post_mortem(&mut self) -> (Option<ExitStatus>, String) {
        self.stdin = None;
        let until = Instant::now() + Duration::from_secs(5);
        let status = loop {
            match self.child.try_wait() {
                Ok(Some(status)) => break Some(status),
                Ok(None) if Instant::now() < until => std::thread::sleep(Duration::from_millis(20)),
                Ok(None) => {
                    self.kill();
                    break self.child.wait().ok();
                }
                Err(_) => break None,
            }
        };
        // Its stderr ends with it (unless a grandchild holds it: then the tail is what came).
        if let Some(t) = self.stderr_thread.take() {
            let until = Instant::now() + Duration::from_secs(2);
            while !t.is_finished() && Instant::now() < until {
                std::thread::sleep(Duration::from_millis(10));
            }
            if t.is_finished() {
                let _ = t.join();
            }
        }
        let tail = self.stderr_tail.lock().unwrap_or_else(|p| p.into_inner());
        (status, tail.iter().cloned().collect::<Vec<_>>().join("\n"))
    }
}

impl Drop for WorkerProcess {
    /// Closing stdin asks the worker to exit; it gets a moment, then SIGKILL.
    fn drop(&mut self) {
        self.stdin = None;
        let until = Instant::now() + Duration::from_millis(500);
        while Instant::now() < until {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        self.kill();
        let _ = self.child.wait();
    }
}

/// "exited with status 1", "was killed by signal 11 (SIGSEGV)", ...
pub fn describe_exit(status: Option<ExitStatus>) -> String {
    use std::os::unix::process::ExitStatusExt;
    match status {
        None => "in an unknown state".into(),
        Some(s) => match (s.code(), s.signal()) {
            (Some(code), _) => format!("exited with status {code}"),
            (None, Some(sig)) => {
                let name = match sig {
                    6 => " (SIGABRT)",
                    9 => " (SIGKILL)",
                    11 => " (SIGSEGV)",
                    15 => " (SIGTERM)",
                    _ => "",
                };
                format!("was killed by signal {sig}{name}")
            }
            _ => format!("{s}"),
        },
    }
}
