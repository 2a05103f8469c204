//! Shared by the cross-process tests: a small demo file, a config, and the server binary as a
//! child. The generic parts (the child guard, the ready line, the HDF5 fork lock, the demo writer)
//! are rfcl-testkit's.
#![allow(dead_code)]
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus};
use std::time::Duration;

use rfcl_proto::auth::{authenticated, AuthChannel, Token};
use rfcl_proto::v1::curriculum_client::CurriculumClient;
use rfcl_testkit::child::{self, ChildGuard};
use rfcl_testkit::demos::SyntheticDemos;
use tonic::transport::Channel;

/// The run token of the test servers.
pub const TEST_TOKEN: &str = "curriculum-test-token-0123";

pub fn test_token() -> Token {
    Token::parse(TEST_TOKEN, "the tests").unwrap()
}

pub const OBS: usize = 3;
pub const ACT: usize = 2;
pub const STATE: usize = rfcl_testkit::demos::STATE_DIM;

/// `n` demos of `t` actions each, succeeding on the last 5 steps; states encode (demo, step).
pub fn write_demos(dir: &Path, n: usize, t: usize) -> PathBuf {
    SyntheticDemos {
        demos: n,
        steps: t,
        obs_dim: OBS,
        action_dim: ACT,
        success_steps: 5,
        max_episode_steps: 100,
        obs: |_, k| k as f32,
        action: |_, _| 0.1,
    }
    .write(dir)
}

pub fn write_config(dir: &Path, lease_timeout_s: f64) -> PathBuf {
    let path = dir.join("config.yml");
    std::fs::write(
        &path,
        format!(
            "name: ctest\nseed: 7\nenv:\n  env_id: PointMaze-v0\n  suite: pointmaze\n  max_episode_steps: 100\n\
             train:\n  num_demos: 3\n  shuffle_demos: false\nreverse:\n  reverse_step_size: 4\n  per_demo_buffer_size: 2\n\
             forward:\n  num_seeds: 10\nservice:\n  snapshot_every_reports: 5\n  lease_timeout_s: {lease_timeout_s}\n"
        ),
    )
    .unwrap();
    path
}

/// `curriculum-server ARGS` with the test token, run to completion (spawned under the HDF5 fork
/// lock).
pub fn run_server(args: &[&str], token: Option<&str>) -> std::process::Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_curriculum-server"));
    cmd.args(args);
    match token {
        Some(token) => child::with_token(&mut cmd, token),
        None => cmd.env_remove("RFCL_TOKEN").env_remove("RFCL_TOKEN_FILE"),
    };
    child::output(&mut cmd)
}

/// A running `curriculum-server` child; killed when dropped.
pub struct ServerProcess {
    pub child: ChildGuard,
    pub grpc: String,
    pub dashboard: String,
}

/// A test run's files in a directory: 3 demos of 20 steps, the test config, and the run
/// directory `dir/run`.
pub struct RunFiles {
    pub demos: PathBuf,
    pub config: PathBuf,
    pub run_dir: PathBuf,
}

impl RunFiles {
    pub fn write(dir: &Path, lease_timeout_s: f64) -> RunFiles {
        RunFiles {
            demos: write_demos(dir, 3, 20),
            config: write_config(dir, lease_timeout_s),
            run_dir: dir.join("run"),
        }
    }

    /// The server's arguments for this run: `--demos D --config C RUN_FLAG RUN_DIR` (`RUN_FLAG`
    /// is `--run-dir` or `--resume`), then `extra`.
    pub fn args<'a>(&'a self, run_flag: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
        let path = |p: &'a PathBuf| p.to_str().unwrap();
        let mut args = vec![
            "--demos",
            path(&self.demos),
            "--config",
            path(&self.config),
            run_flag,
            path(&self.run_dir),
        ];
        args.extend_from_slice(extra);
        args
    }
}

impl ServerProcess {
    /// Writes a test run's files into `dir` ([`RunFiles`]), then starts a server on them.
    pub fn start_fresh(dir: &Path, lease_timeout_s: f64) -> ServerProcess {
        let files = RunFiles::write(dir, lease_timeout_s);
        ServerProcess::start(&files.args("--run-dir", &[]))
    }

    pub fn start(args: &[&str]) -> ServerProcess {
        Self::start_with_env(args, &[])
    }

    /// Starts the server with extra environment variables.
    pub fn start_with_env(args: &[&str], env: &[(&str, &Path)]) -> ServerProcess {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_curriculum-server"));
        cmd.args(args).envs(env.iter().map(|(k, v)| (k, v)));
        Self::start_command(cmd)
    }

    /// Starts the server with at most `files` open file descriptors (util-linux `prlimit`).
    pub fn start_with_file_limit(args: &[&str], files: u32) -> ServerProcess {
        let mut cmd = Command::new("prlimit");
        cmd.arg(format!("--nofile={files}:{files}"))
            .arg(env!("CARGO_BIN_EXE_curriculum-server"))
            .args(args);
        Self::start_command(cmd)
    }

    fn start_command(mut cmd: Command) -> ServerProcess {
        let (child, ready) =
            child::start_service("curriculum-server", child::with_token(&mut cmd, TEST_TOKEN));
        ServerProcess {
            grpc: ready.grpc_url().expect("a grpc= address on the ready line"),
            dashboard: ready.expect_field("dashboard").to_string(),
            child,
        }
    }

    /// A client that carries the run's token.
    pub async fn client(&self) -> CurriculumClient<AuthChannel> {
        CurriculumClient::new(authenticated(self.channel().await, &test_token()))
    }

    /// A bare connection: calls on it carry no token.
    pub async fn channel(&self) -> Channel {
        Channel::from_shared(self.grpc.clone())
            .unwrap()
            .connect()
            .await
            .expect("connecting to the curriculum server")
    }

    /// `GET <dashboard>PATH` with curl (`api/state`, `metrics`): the body; panics when it fails.
    pub fn dashboard_get(&self, path: &str) -> String {
        let out =
            child::output(Command::new("curl").args(["-sf", &format!("{}{path}", self.dashboard)]));
        assert!(out.status.success(), "GET {path} failed ({})", out.status);
        String::from_utf8(out.stdout).unwrap()
    }

    /// The dashboard's view (`/api/state`): the run's state and what only the page shows
    /// (forward levels, open leases, actors).
    pub fn view(&self) -> rfcl_curriculum::dashboard::DashboardView {
        serde_json::from_str(&self.dashboard_get("api/state")).expect("/api/state is a view")
    }

    pub fn sigkill(&mut self) {
        self.child.sigkill();
    }

    /// SIGTERM and wait: the server writes its final snapshot.
    pub fn sigterm(&mut self) -> ExitStatus {
        self.child.sigterm(Duration::from_secs(60))
    }
}
