//! Shared by the cross-process tests: a small demo file, a config, and the server binary as a child.
#![allow(dead_code)]
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use rfcl_core::demo::{Demo, DemoSet, ResetArgs, StateLayout, SuccessSource};
use rfcl_proto::auth::{authenticated, AuthChannel, Token};
use rfcl_proto::v1::curriculum_client::CurriculumClient;
use tonic::transport::Channel;

/// The run token of the test servers.
pub const TEST_TOKEN: &str = "curriculum-test-token-0123";

pub fn test_token() -> Token {
    Token::parse(TEST_TOKEN, "the tests").unwrap()
}

/// HDF5 opens files without O_CLOEXEC and holds a flock on them: a child forked while another test
/// thread has a demo file open would inherit that lock for its whole life. Writing, reading and
/// spawning take this lock so no fork happens while an HDF5 file is open in this process.
pub static HDF5_FORK_LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());

pub fn hdf5_fork_guard() -> std::sync::MutexGuard<'static, ()> {
    HDF5_FORK_LOCK.lock().unwrap_or_else(|p| p.into_inner())
}

pub const OBS: usize = 3;
pub const ACT: usize = 2;
pub const STATE: usize = 4;

/// `n` demos of `t` actions each, succeeding on the last 5 steps; states encode (demo, step).
pub fn write_demos(dir: &Path, n: usize, t: usize) -> PathBuf {
    let demos = (0..n)
        .map(|i| Demo {
            episode_id: i as u64,
            obs_dim: OBS,
            action_dim: ACT,
            state_dim: STATE,
            obs: (0..(t + 1) * OBS).map(|k| k as f32).collect(),
            actions: vec![0.1; t * ACT],
            success: (0..t).map(|s| s + 5 >= t).collect(),
            env_states: (0..=t)
                .flat_map(|s| [i as f32, s as f32, 0.5, -0.5])
                .collect(),
            succeeded: true,
            success_source: SuccessSource::Steps,
            reset: ResetArgs {
                seed: Some(100 + i as u64),
                options: serde_json::json!({}),
            },
        })
        .collect();
    let path = dir.join("demos.h5");
    let _guard = hdf5_fork_guard();
    DemoSet {
        path: path.clone(),
        sidecar: None,
        env_id: Some("PointMaze-v0".into()),
        env_info: serde_json::json!({"env_id": "PointMaze-v0", "env_kwargs": {}, "max_episode_steps": 100}),
        control_mode: None,
        obs_dim: OBS,
        action_dim: ACT,
        state_dim: STATE,
        state_layout: StateLayout::flat(STATE),
        demos,
    }
    .write(&path)
    .expect("writing the test demos");
    path
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

/// A running `curriculum-server` child; killed when dropped.
pub struct ServerProcess {
    pub child: Child,
    pub grpc: String,
    pub dashboard: String,
}

impl ServerProcess {
    /// Writes 3 demos of 20 steps and the test config into `dir`, then starts a server on them
    /// with its run directory in `dir/run`.
    pub fn start_fresh(dir: &Path, lease_timeout_s: f64) -> ServerProcess {
        let demos = write_demos(dir, 3, 20);
        let config = write_config(dir, lease_timeout_s);
        let run_dir = dir.join("run");
        ServerProcess::start(&[
            "--demos",
            demos.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
            "--run-dir",
            run_dir.to_str().unwrap(),
        ])
    }

    pub fn start(args: &[&str]) -> ServerProcess {
        Self::start_with_env(args, &[])
    }

    /// Starts the server with extra environment variables.
    pub fn start_with_env(args: &[&str], env: &[(&str, &Path)]) -> ServerProcess {
        let guard = hdf5_fork_guard();
        let mut child = Command::new(env!("CARGO_BIN_EXE_curriculum-server"))
            .args(args)
            .envs(env.iter().map(|(k, v)| (k, v)))
            .env("RFCL_TOKEN", TEST_TOKEN)
            .env_remove("RFCL_TOKEN_FILE")
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("starting curriculum-server");
        drop(guard);
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        let grpc = line
            .split("grpc=")
            .nth(1)
            .and_then(|s| s.split_whitespace().next());
        let dashboard = line
            .split("dashboard=")
            .nth(1)
            .map(|s| s.trim().to_string());
        match (grpc, dashboard) {
            (Some(g), Some(d)) => ServerProcess {
                grpc: format!("http://{g}"),
                dashboard: d,
                child,
            },
            _ => {
                let status = child.wait().unwrap();
                panic!("curriculum-server did not start ({status}); its first line was {line:?}")
            }
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

    pub fn sigkill(&mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }

    /// SIGTERM and wait: the server writes its final snapshot.
    pub fn sigterm(&mut self) -> std::process::ExitStatus {
        Command::new("kill")
            .arg("-TERM")
            .arg(self.child.id().to_string())
            .status()
            .unwrap();
        self.child.wait().unwrap()
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
