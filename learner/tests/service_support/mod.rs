//! Shared by the learner's cross-process tests (`service_*.rs`): small demo files and configs, the
//! `curriculum-server` and `learner` binaries as children on 127.0.0.1:0, transition batches. The
//! generic parts (the child guard, the ready line, the HDF5 fork lock, the demo writer, finding
//! and building the `curriculum-server` binary) are rfcl-testkit's.
#![allow(dead_code)]
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus};
use std::time::{Duration, Instant};

use rfcl_core::transition::{RecordLayout, Transition};
use rfcl_proto::auth::{authenticated, AuthChannel, Token};
use rfcl_proto::v1;
use rfcl_proto::v1::curriculum_client::CurriculumClient;
use rfcl_proto::v1::learner_client::LearnerClient;
use rfcl_testkit::child::{self, ChildGuard, ReadyLine};
use rfcl_testkit::demos::SyntheticDemos;
use tonic::transport::Channel;

pub const OBS: usize = 4;
pub const ACT: usize = 2;
/// Actions per demo.
pub const DEMO_LEN: usize = 12;
pub const DEMOS: usize = 3;

/// `DEMOS` demos of `DEMO_LEN` steps, succeeding on the last 4 steps, actions in [-0.8, 0.8].
pub fn write_demos(dir: &Path) -> PathBuf {
    SyntheticDemos {
        demos: DEMOS,
        steps: DEMO_LEN,
        obs_dim: OBS,
        action_dim: ACT,
        success_steps: 4,
        max_episode_steps: 50,
        obs: |i, k| ((k + i) as f32 * 0.1).sin(),
        action: |i, k| 0.8 * ((k * 3 + i) as f32 * 0.7).cos(),
    }
    .write(dir)
}

/// The schedule of the test config: K = num_envs · steps_per_env = 4 env steps per iteration,
/// G = 2 critic updates, W = `seed_steps` warm-up steps.
pub const K: u64 = 4;
pub const G: u64 = 2;

/// A small, fast config (16-wide networks, 2 critics) with `extra` YAML lines appended under the
/// given sections (`sac`, `train`: see the format string).
pub fn write_config(dir: &Path, seed_steps: u64, steps: u64, sac_extra: &str) -> PathBuf {
    let path = dir.join("config.yml");
    std::fs::write(
        &path,
        format!(
            "name: ltest\nseed: 3\n\
             env:\n  env_id: PointMaze-v0\n  suite: pointmaze\n  max_episode_steps: 50\n  num_envs: 2\n\
             train:\n  steps: {steps}\n  num_demos: {DEMOS}\n  shuffle_demos: false\n\
             sac:\n  num_seed_steps: {seed_steps}\n  replay_buffer_capacity: 1000\n  batch_size: 16\n  steps_per_env: 2\n  \
             grad_updates_per_step: 2\n  actor_update_freq: 1\n  critic_ensemble: 2\n  target_pool: 2\n  \
             log_freq: 20\n  save_freq: 40\n{sac_extra}\
             network:\n  actor_features: [16, 16]\n  critic_features: [16, 16]\n\
             reverse:\n  reverse_step_size: 50\n  per_demo_buffer_size: 1\n\
             forward:\n  num_seeds: 10\n\
             service:\n  num_actors: 1\n"
        ),
    )
    .unwrap();
    path
}

/// Adds `keys` (YAML lines, each indented by two spaces) to the `train:` section of a config
/// written by [`write_config`].
pub fn add_train_keys(config: &Path, keys: &str) {
    let text = std::fs::read_to_string(config).unwrap().replace(
        "  shuffle_demos: false\n",
        &format!("  shuffle_demos: false\n{keys}"),
    );
    std::fs::write(config, text).unwrap();
}

/// The run token of the test services.
pub const TEST_TOKEN: &str = "learner-test-token-0123";

/// A channel to `url` whose calls carry [`TEST_TOKEN`].
pub async fn connect(url: &str) -> AuthChannel {
    let channel = Channel::from_shared(url.to_string())
        .unwrap()
        .connect()
        .await
        .unwrap();
    authenticated(channel, &Token::parse(TEST_TOKEN, "the tests").unwrap())
}

/// A running `curriculum-server` child (built by rfcl-testkit when missing); killed when dropped.
pub struct Curriculum {
    pub child: ChildGuard,
    pub grpc: String,
}

impl Curriculum {
    pub fn start(config: &Path, demos: &Path, run_dir: &Path) -> Curriculum {
        let mut cmd = Command::new(rfcl_testkit::binaries::curriculum_server());
        child::with_token(&mut cmd, TEST_TOKEN)
            .args(["--config".as_ref(), config.as_os_str()])
            .args(["--demos".as_ref(), demos.as_os_str()])
            .args(["--run-dir".as_ref(), run_dir.as_os_str()]);
        let (child, ready) = child::start_service("curriculum-server", &mut cmd);
        Curriculum {
            child,
            grpc: ready.grpc_url().expect("a grpc= address on the ready line"),
        }
    }

    pub async fn client(&self) -> CurriculumClient<AuthChannel> {
        CurriculumClient::new(connect(&self.grpc).await)
    }

    /// Acquires and reports successful episodes until stage 2 begins (spec 2.7); returns its
    /// stage epoch.
    pub async fn drive_to_stage_2(&self) -> u64 {
        let mut client = self.client().await;
        for _ in 0..5000 {
            let lease = client
                .acquire(v1::AcquireRequest {
                    actor_id: 9,
                    env_index: 0,
                    eval: false,
                })
                .await
                .unwrap()
                .into_inner();
            if lease.stage == 2 {
                return lease.stage_epoch;
            }
            let ack = client
                .report(success_report(&lease))
                .await
                .unwrap()
                .into_inner();
            if ack.stage == 2 {
                return ack.stage_epoch;
            }
        }
        panic!("stage 1 did not end within 5000 successful episodes");
    }
}

/// A successful 5-step episode of `lease` by actor 9, as a test reports it to the curriculum server.
pub fn success_report(lease: &v1::ResetLease) -> v1::EpisodeReport {
    v1::EpisodeReport {
        lease_id: lease.lease_id,
        success_at_end: true,
        success_once: true,
        episode_return: 1.0,
        length: 5,
        policy_version: 0,
        stage_epoch: lease.stage_epoch,
        actor_id: 9,
        actor_env_steps: 0,
        policy_env_steps: 0,
        actor_sim_restarts: 0,
        reset_failure: String::new(),
    }
}

/// A run in `dir/run` served by real processes: its config, its curriculum server and its
/// learner.
pub struct Pair {
    pub config: PathBuf,
    pub run_dir: PathBuf,
    pub curriculum: Curriculum,
    pub learner: Learner,
}

impl Pair {
    /// The run of `config` (written in `dir`) on synthetic demos written in `dir`: its curriculum
    /// server, and a learner started with `flags` after the usual arguments.
    pub fn start(dir: &Path, config: PathBuf, flags: &[&str]) -> Pair {
        let demos = write_demos(dir);
        let run_dir = dir.join("run");
        let curriculum = Curriculum::start(&config, &demos, &run_dir);
        let args = Learner::args(&config, &curriculum.grpc, &demos, &run_dir);
        let mut args: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
        args.extend(flags.iter().map(std::ffi::OsStr::new));
        let learner = Learner::start(&args);
        Pair {
            config,
            run_dir,
            curriculum,
            learner,
        }
    }
}

/// [`Pair::start`] of a config written by [`write_config`] (warm-up `seed_steps`, budget `steps`,
/// `sac_extra` lines).
pub fn start_pair(
    dir: &Path,
    seed_steps: u64,
    steps: u64,
    sac_extra: &str,
    flags: &[&str],
) -> Pair {
    Pair::start(dir, write_config(dir, seed_steps, steps, sac_extra), flags)
}

/// [`start_pair`] (warm-up `seed_steps`, a budget no test reaches) in `utd_mode: sync` with a
/// 2-batch ingest queue: data can never run ahead of the updates.
pub fn start_sync_pair(dir: &Path, seed_steps: u64) -> Pair {
    start_pair(
        dir,
        seed_steps,
        100_000,
        "  utd_mode: sync\n",
        &["--queue-batches", "2"],
    )
}

/// A running `learner` child; killed when dropped. Its stderr is kept (`RFCL_TEST_LOGS=1` shows
/// it as it comes).
pub struct Learner {
    pub child: ChildGuard,
    pub grpc: String,
}

/// `learner ARGS` with the test token, not yet started.
pub fn learner_command(args: &[&std::ffi::OsStr]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_learner"));
    child::with_token(&mut cmd, TEST_TOKEN).args(args);
    cmd
}

/// Runs the learner binary with `args` to completion (for start-up failures): exit status, stdout
/// and stderr.
pub fn run_learner(args: &[&std::ffi::OsStr]) -> (ExitStatus, String, String) {
    let out = child::output(&mut learner_command(args));
    (
        out.status,
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

impl Learner {
    /// Starts `learner --threads 1 ARGS` and waits for its ready line.
    pub fn start(args: &[&std::ffi::OsStr]) -> Learner {
        Self::start_with_threads(1, args)
    }

    /// Starts `learner --threads THREADS ARGS` and waits for its ready line.
    pub fn start_with_threads(threads: u32, args: &[&std::ffi::OsStr]) -> Learner {
        let threads = threads.to_string();
        let mut all: Vec<&std::ffi::OsStr> = vec!["--threads".as_ref(), threads.as_ref()];
        all.extend_from_slice(args);
        Self::start_command(&mut learner_command(&all)).0
    }

    /// Starts `cmd` (a [`learner_command`]) and waits for its ready line.
    pub fn start_command(cmd: &mut Command) -> (Learner, ReadyLine) {
        let (child, ready) = child::start_service("learner", cmd.env("OMP_WAIT_POLICY", "PASSIVE"));
        assert!(
            ready.line.starts_with("learner ready grpc="),
            "unexpected ready line {:?}",
            ready.line
        );
        let grpc = ready.grpc_url().expect("a grpc= address on the ready line");
        (Learner { child, grpc }, ready)
    }

    /// The child's stderr so far; all of it once the child has exited.
    pub fn stderr_text(&mut self) -> String {
        self.child.stderr_text()
    }

    /// The usual arguments: config, curriculum, demos, run dir.
    pub fn args(
        config: &Path,
        curriculum: &str,
        demos: &Path,
        run_dir: &Path,
    ) -> Vec<std::ffi::OsString> {
        vec![
            "--config".into(),
            config.into(),
            "--curriculum".into(),
            curriculum.into(),
            "--demos".into(),
            demos.into(),
            "--run-dir".into(),
            run_dir.into(),
        ]
    }

    pub async fn client(&self) -> LearnerClient<AuthChannel> {
        LearnerClient::new(connect(&self.grpc).await)
    }

    pub fn sigkill(&mut self) {
        self.child.sigkill();
    }

    /// SIGTERM and wait: the learner writes its final checkpoint and exports the policy.
    pub fn sigterm(&mut self) -> ExitStatus {
        self.child.sigterm(Duration::from_secs(60))
    }

    /// Waits for the child to exit on its own.
    pub fn wait(&mut self, limit: Duration) -> ExitStatus {
        self.child.wait_within(limit)
    }
}

/// Transition `i` of a deterministic stream (values depend on `i` only).
pub fn transition(i: u64, stage_epoch: u64, policy_version: u64) -> Transition {
    let x = i as f32;
    Transition {
        obs: (0..OBS).map(|k| (x * 0.13 + k as f32).sin()).collect(),
        action: (0..ACT)
            .map(|k| (x * 0.29 + k as f32).cos() * 0.9)
            .collect(),
        reward: if i.is_multiple_of(5) { 1.0 } else { 0.0 },
        next_obs: (0..OBS)
            .map(|k| ((x + 1.0) * 0.13 + k as f32).sin())
            .collect(),
        mask: 1.0,
        stage_epoch,
        actor_id: 1,
        policy_version,
    }
}

/// Transitions `range` as batches of `per_batch`.
pub fn batches(
    range: std::ops::Range<u64>,
    per_batch: usize,
    stage_epoch: u64,
) -> Vec<v1::TransitionBatch> {
    let layout = RecordLayout::new(OBS, ACT);
    let all: Vec<Transition> = range.map(|i| transition(i, stage_epoch, 0)).collect();
    all.chunks(per_batch)
        .map(|chunk| {
            let mut records = vec![0; chunk.len() * layout.record_bytes()];
            layout.encode_batch(chunk, &mut records).unwrap();
            v1::TransitionBatch {
                actor_id: 1,
                obs_dim: OBS as u32,
                action_dim: ACT as u32,
                count: chunk.len() as u32,
                records,
            }
        })
        .collect()
}

/// Pushes `batches` in one `PushTransitions` stream.
pub async fn push(
    client: &mut LearnerClient<AuthChannel>,
    batches: Vec<v1::TransitionBatch>,
) -> Result<v1::PushSummary, tonic::Status> {
    client
        .push_transitions(tokio_stream::iter(batches))
        .await
        .map(|r| r.into_inner())
}

pub async fn health(client: &mut LearnerClient<AuthChannel>) -> v1::HealthReply {
    client
        .health(v1::HealthRequest {})
        .await
        .unwrap()
        .into_inner()
}

/// Polls Health until `done` holds (panics after `limit`).
pub async fn wait_health(
    client: &mut LearnerClient<AuthChannel>,
    limit: Duration,
    done: impl Fn(&v1::HealthReply) -> bool,
) -> v1::HealthReply {
    let start = Instant::now();
    loop {
        let h = health(client).await;
        if done(&h) {
            return h;
        }
        assert!(
            start.elapsed() < limit,
            "condition not met within {limit:?}; last health {h:?}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Iterations the spec 5.4 schedule grants after `n` env steps with warm-up `w` (one phase).
pub fn earned(n: u64, w: u64) -> u64 {
    (n / K).saturating_sub(w.div_ceil(K))
}
