//! Shared by the whole-run tests (`tests/train_*.rs`): demos made by `rfcl demos generate`, `rfcl
//! train` as a child process, and the running services' own counters read over gRPC.
//!
//! No demo file is ever opened in a test process: the demos are written by the `rfcl` child, so no
//! HDF5 handle (opened without O_CLOEXEC, with a flock) can leak into a forked child. The child
//! guard and the service binaries are rfcl-testkit's.
#![allow(dead_code)]
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use rfcl_testkit::child::{self, ChildGuard};

use rfcl_proto::auth::{authenticated, AuthChannel, Token};
use rfcl_proto::v1;
use rfcl_proto::v1::learner_client::LearnerClient;
use serde_json::Value;

// Not every test that includes this module signals.
#[allow(unused_imports)]
pub use rfcl_testkit::child::{signal, succeed};

pub mod sim;

/// The documented fast test config.
pub fn test_config() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/pointmaze_test.yml")
}

fn rfcl() -> &'static str {
    env!("CARGO_BIN_EXE_rfcl")
}

/// The services `rfcl train` starts must be built next to `rfcl` (it runs them from its own
/// directory): rfcl-testkit builds any that is missing.
pub fn require_services() {
    let dir = std::fs::canonicalize(Path::new(rfcl()).parent().unwrap()).unwrap();
    for path in [
        rfcl_testkit::binaries::curriculum_server(),
        rfcl_testkit::binaries::learner(),
        rfcl_testkit::binaries::actor(),
    ] {
        let found = std::fs::canonicalize(path.parent().unwrap()).unwrap();
        assert_eq!(found, dir, "{} is not next to rfcl", path.display());
    }
}

/// 5 PointMaze demos in `dir`, written by `rfcl demos generate`.
pub fn generate_demos(dir: &Path) -> PathBuf {
    generate_env_demos("pointmaze", 5, &dir.join("demos.h5"))
}

/// `rfcl demos generate --env ENV -n N --out OUT`; returns `out`.
pub fn generate_env_demos(env: &str, n: u32, out: &Path) -> PathBuf {
    generate_env_demos_from(env, n, 0, out)
}

/// [`generate_env_demos`] from the generator's seed `seed` (`--seed`).
pub fn generate_env_demos_from(env: &str, n: u32, seed: u64, out: &Path) -> PathBuf {
    let (n, seed) = (n.to_string(), seed.to_string());
    succeed(
        Command::new(rfcl())
            .args([
                "demos", "generate", "--env", env, "-n", &n, "--seed", &seed, "--out",
            ])
            .arg(out),
    );
    out.to_path_buf()
}

/// The mean success of the last 5 evaluations at which the whole-run tests stop.
pub const BAR: f64 = 0.9;

/// The override that stops a run at [`BAR`].
pub fn stop_at_bar() -> String {
    format!("service.stop_at_eval_success={BAR}")
}

/// `rfcl train` of the documented test config on 5 PointMaze demos generated in `dir`, with
/// `overrides` (config overrides and flags) after the dataset's path; the run directory is
/// `dir/run` (`Training::run_dir`), rfcl's stderr goes to `dir/<log>`.
pub fn start_test_run(dir: &Path, overrides: &[String], log: &str) -> Training {
    require_services();
    let demos = generate_demos(dir);
    start_run(
        &test_config(),
        &demos,
        overrides,
        &dir.join("run"),
        &dir.join(log),
    )
}

/// `rfcl train CONFIG train.dataset_path=DEMOS OVERRIDES... --run-dir RUN_DIR`, its stderr to
/// `log`.
pub fn start_run(
    config: &Path,
    demos: &Path,
    overrides: &[String],
    run_dir: &Path,
    log: &Path,
) -> Training {
    Training::start(&train_args(config, demos, overrides, run_dir), run_dir, log)
}

/// The arguments of `rfcl train` for [`start_run`].
pub fn train_args(
    config: &Path,
    demos: &Path,
    overrides: &[String],
    run_dir: &Path,
) -> Vec<String> {
    let mut args = vec![
        config.display().to_string(),
        format!("train.dataset_path={}", demos.display()),
    ];
    args.extend_from_slice(overrides);
    args.extend(["--run-dir".to_string(), run_dir.display().to_string()]);
    args
}

/// A running `rfcl train`: stdout lines are collected, stderr goes to a file. Dropped while it
/// runs, it gets SIGTERM (rfcl stops its children then) and 60 s before SIGKILL.
pub struct Training {
    child: ChildGuard,
    pub stderr_path: PathBuf,
    pub run_dir: PathBuf,
}

impl Training {
    /// `rfcl train <args>`; `run_dir` is where the run lives (for the helpers). SIGINT starts as
    /// its default whatever this test process inherited (rfcl keeps an inherited "ignore": the
    /// Unix convention), so that the tests' Ctrl-C reaches it.
    pub fn start(args: &[String], run_dir: &Path, log: &Path) -> Training {
        let mut command = Command::new("env");
        command.arg("--default-signal=INT").arg(rfcl());
        Self::spawn(command, args, run_dir, log)
    }

    /// `rfcl train <args>` started with SIGINT ignored, as a shell script's background job is.
    pub fn start_ignoring_sigint(args: &[String], run_dir: &Path, log: &Path) -> Training {
        let mut command = Command::new("sh");
        command
            .args(["-c", "trap '' INT; exec \"$0\" \"$@\""])
            .arg(rfcl());
        Self::spawn(command, args, run_dir, log)
    }

    fn spawn(mut command: Command, args: &[String], run_dir: &Path, log: &Path) -> Training {
        let stderr = std::fs::File::create(log).unwrap();
        let child = child::spawn_locked(
            command
                .arg("train")
                .args(args)
                .stdin(Stdio::null())
                .stdout(Stdio::piped())
                .stderr(stderr),
        )
        .unwrap();
        Training {
            child: ChildGuard::new("rfcl train", child).terminate_on_drop(Duration::from_secs(60)),
            stderr_path: log.to_path_buf(),
            run_dir: run_dir.to_path_buf(),
        }
    }

    /// rfcl's stdout lines so far.
    pub fn stdout_lines(&self) -> Vec<String> {
        self.child.stdout_lines()
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn stderr(&self) -> String {
        std::fs::read_to_string(&self.stderr_path).unwrap_or_default()
    }

    /// Waits until rfcl's stderr holds `line`; panics with the stderr after `limit`. rfcl says
    /// what it did after doing it (a respawned actor is in processes.json a moment before the
    /// line), so a test that saw the effect waits for the words too.
    pub fn wait_for_stderr(&self, line: &str, limit: Duration) {
        if wait_for(limit, || self.stderr().contains(line).then_some(())).is_none() {
            panic!(
                "no {line:?} within {limit:?} in rfcl's stderr:\n{}",
                self.stderr()
            );
        }
    }

    pub fn exited(&mut self) -> Option<ExitStatus> {
        self.child.try_wait().unwrap()
    }

    /// Waits for the exit; panics with rfcl's stderr after `limit`.
    pub fn wait(&mut self, limit: Duration) -> ExitStatus {
        let until = Instant::now() + limit;
        loop {
            if let Some(status) = self.exited() {
                return status;
            }
            if Instant::now() > until {
                panic!(
                    "rfcl train did not finish within {limit:?}; its stderr:\n{}",
                    self.stderr()
                );
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// `RUN_DIR/processes.json` once the session has started all its children.
    pub fn processes(&self, limit: Duration) -> Value {
        let path = self.run_dir.join("processes.json");
        let until = Instant::now() + limit;
        loop {
            if let Some(v) = std::fs::read_to_string(&path)
                .ok()
                .and_then(|t| serde_json::from_str::<Value>(&t).ok())
            {
                return v;
            }
            assert!(
                Instant::now() < until,
                "no processes.json within {limit:?}:\n{}",
                self.stderr()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    pub fn summary(&self) -> Value {
        let path = self.run_dir.join("summary.json");
        let text = std::fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("{}: {e}\n{}", path.display(), self.stderr()));
        serde_json::from_str(&text).unwrap()
    }
}

/// Whether `pid` is a live process (not gone, not a zombie).
pub fn alive(pid: u64) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Ok(stat) => stat
            .rsplit(')')
            .next()
            .and_then(|rest| rest.split_whitespace().next())
            .is_some_and(|state| state != "Z" && state != "X"),
        Err(_) => false,
    }
}

/// Every pid in a processes.json.
pub fn child_pids(processes: &Value) -> Vec<u64> {
    processes["children"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["pid"].as_u64().unwrap())
        .collect()
}

/// The pid of child `name` in a processes.json.
pub fn child_pid(processes: &Value, name: &str) -> u64 {
    processes["children"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == name)
        .unwrap_or_else(|| panic!("no {name} in {processes}"))["pid"]
        .as_u64()
        .unwrap()
}

/// The run token of services a test starts itself (not through `rfcl train`).
pub const TEST_TOKEN: &str = "whole-run-test-token-0123";

/// A channel to `addr` whose calls carry the run's token: the one in the file processes.json
/// names (`rfcl train` made it), else [`TEST_TOKEN`].
async fn connect(processes: &Value, addr: String) -> Option<AuthChannel> {
    let token = match processes["token_file"].as_str() {
        Some(path) => Token::read_file(Path::new(path)).ok()?,
        None => Token::parse(TEST_TOKEN, "the tests").unwrap(),
    };
    let channel = tonic::transport::Channel::from_shared(addr)
        .ok()?
        .connect()
        .await
        .ok()?;
    Some(authenticated(channel, &token))
}

/// The learner's Health (env steps received, critic updates, policy version).
pub fn learner_health(processes: &Value) -> Option<v1::HealthReply> {
    let addr = processes["learner"].as_str()?.to_string();
    block_on(async move {
        let mut c = LearnerClient::new(connect(processes, addr).await?);
        c.health(v1::HealthRequest {})
            .await
            .ok()
            .map(|r| r.into_inner())
    })
}

/// The curriculum server's dashboard view (`/api/state`: the run's state with the actor rows,
/// levels and learner panel the page shows), `None` while it does not answer.
pub fn curriculum_state(processes: &Value) -> Option<Value> {
    let dashboard = processes["dashboard"].as_str()?;
    let out = Command::new("curl")
        .args(["-sf", "-m", "5", &format!("{dashboard}api/state")])
        .output()
        .ok()?;
    if !out.status.success() {
        return None;
    }
    serde_json::from_slice(&out.stdout).ok()
}

fn block_on<T>(f: impl std::future::Future<Output = T>) -> T {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(f)
}

/// Polls `probe` every 250 ms until it returns `Some`, for at most `limit`.
pub fn wait_for<T>(limit: Duration, mut probe: impl FnMut() -> Option<T>) -> Option<T> {
    let until = Instant::now() + limit;
    loop {
        if let Some(v) = probe() {
            return Some(v);
        }
        if Instant::now() > until {
            return None;
        }
        std::thread::sleep(Duration::from_millis(250));
    }
}

/// `rfcl eval RUN_DIR -n N`: (success at the end, its output line).
pub fn eval_run(run_dir: &Path, episodes: u32) -> (f64, String) {
    let stdout = succeed(
        Command::new(rfcl())
            .arg("eval")
            .arg(run_dir)
            .args(["-n", &episodes.to_string()]),
    );
    let success = stdout
        .split("success ")
        .nth(1)
        .and_then(|s| s.split('%').next())
        .and_then(|s| s.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no success rate in {stdout:?}"));
    (success / 100.0, stdout)
}

/// The summary's checks every finished run must pass: it reached `bar` by the running mean of its
/// last 5 evals, the milestones are consistent, and the processes' own counters show that
/// transitions and leases flowed.
pub fn assert_reached(summary: &Value, bar: f64) {
    assert_eq!(summary["ending"], "eval_success", "{summary:#}");
    let mean = summary["eval_success_mean_last_5"].as_f64().unwrap();
    assert!(mean >= bar, "mean of the last 5 evals {mean} < {bar}");
    let ci: Vec<f64> = summary["eval_success_last_5_ci95"]
        .as_array()
        .unwrap_or_else(|| panic!("no eval_success_last_5_ci95 in {summary:#}"))
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert!(
        ci[0] <= mean && mean <= ci[1] && ci[1] <= 1.0,
        "{ci:?} around {mean}"
    );
    let evals = summary["evals"].as_array().unwrap();
    assert!(evals.len() >= 5, "{summary:#}");
    for e in evals {
        assert!(e["episodes"].as_u64().unwrap() >= 34, "{e}");
    }
    let env_steps = summary["env_steps"].as_u64().unwrap();
    let updates = summary["updates"].as_u64().unwrap();
    let curriculum_steps = summary["curriculum_env_steps"].as_u64().unwrap();
    assert!(env_steps > 0 && updates > 0, "{summary:#}");
    assert!(summary["curriculum_episodes"].as_u64().unwrap() > 0);
    // What the curriculum saw reported and what the learner received agree, up to the episodes
    // in flight (8 envs × 300 steps), those whose leases were lost, and the steps a restarted
    // learner rolled back to its checkpoint (the accounting below checks each bound exactly).
    let rolled_back = summary["env_steps_accounting"]["learner_rolled_back"]
        .as_u64()
        .unwrap_or_else(|| panic!("no learner_rolled_back in {summary:#}"));
    assert!(
        curriculum_steps <= env_steps + 8 * 300 + rolled_back
            && curriculum_steps * 10 >= env_steps * 9,
        "curriculum {curriculum_steps} vs learner {env_steps} env steps ({rolled_back} rolled back)"
    );
    assert_eq!(
        summary["env_steps_accounting"]["explained"], true,
        "the counted losses do not explain the difference: {summary:#}"
    );
    // The first eval at or above each threshold the run passed, by env steps, within the run.
    let mut previous = 0;
    for m in summary["to_success"].as_array().unwrap() {
        let threshold = m["threshold"].as_f64().unwrap();
        match m["env_steps"].as_u64() {
            Some(steps) => {
                assert!(previous <= steps && steps <= env_steps, "{summary:#}");
                assert!(m["wall_s"].as_f64().unwrap() <= summary["wall_s"].as_f64().unwrap());
                previous = steps;
            }
            // The mean of the last 5 reached the bar, so one of them did.
            None => assert!(threshold > bar, "{threshold} not reached: {summary:#}"),
        }
    }
}
