//! The `actor` binary over real gRPC on loopback, against the real `curriculum-server` binary and
//! a learner double served from this test (the rfcl.v1.Learner contract: run info, a transition
//! stream it decodes and checks, policies it publishes from a real SAC actor network).
//!
//! * a train actor takes leases, explores uniformly, then acts with the published policy, streams
//!   well-formed transitions and reports every episode;
//! * an eval actor evaluates each policy that passes a multiple of `sac.eval_freq`, with the number
//!   of episodes of spec 5.7, aggregated by the curriculum server per policy version;
//! * a dead learner or curriculum server makes the actor exit non-zero with a clear error;
//! * with `train.data_action_scale` the envs get the agent action over the learner's scale,
//!   clipped (spec 6.4), transitions keep the agent action, and a malformed or missing scale is
//!   refused at start;
//! * an unsupported suite is refused at start.
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::process::{Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rfcl_actor::pointmaze::demos::{demo_set, generate_demos};
use rfcl_core::config::{resolve_file, to_yaml, RunConfig};
use rfcl_core::transition::{RecordLayout, Transition};
use rfcl_proto::auth::{Guard, Token};
use rfcl_proto::v1;
use rfcl_proto::v1::learner_server::{Learner, LearnerServer};
use rfcl_testkit::child::{self, ChildGuard};
use tokio::sync::watch;
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status, Streaming};

fn write_run(dir: &Path, extra: &str) -> (PathBuf, PathBuf, RunConfig) {
    let demos = dir.join("demos.h5");
    rfcl_testkit::demos::write_demo_set(&demo_set(generate_demos(3, 0), &demos), &demos);
    let config = dir.join("config.yml");
    std::fs::write(
        &config,
        format!(
            "base_config: {}/../configs/pointmaze.yml\nname: actor_test\nseed: 5\n\
             train:\n  dataset_path: {}\n  num_demos: 3\nsac:\n  num_seed_steps: 200\n  eval_freq: 1000\n\
             eval_env:\n  num_envs: 2\nservice:\n  transition_batch: 16\n{extra}",
            env!("CARGO_MANIFEST_DIR"),
            demos.display()
        ),
    )
    .unwrap();
    let cfg = resolve_file(&config, &[]).unwrap();
    (config, demos, cfg)
}

/// The run token of the test services.
const TEST_TOKEN: &str = "actor-test-token-0123456";

fn test_token() -> Token {
    Token::parse(TEST_TOKEN, "the tests").unwrap()
}

/// The `curriculum-server` binary (built by rfcl-testkit when missing); killed when dropped.
struct Server {
    _child: ChildGuard,
    grpc: String,
    /// The dashboard's URL, with its trailing slash.
    dashboard: String,
}

impl Server {
    fn start(config: &Path, demos: &Path, run_dir: &Path) -> Server {
        let mut cmd = Command::new(rfcl_testkit::binaries::curriculum_server());
        cmd.arg("--config")
            .arg(config)
            .arg("--demos")
            .arg(demos)
            .arg("--run-dir")
            .arg(run_dir)
            .env("RUST_LOG", "warn");
        let (child, ready) =
            child::start_service("curriculum-server", child::with_token(&mut cmd, TEST_TOKEN));
        Server {
            _child: child,
            grpc: ready.expect_field("grpc").to_string(),
            dashboard: ready.expect_field("dashboard").to_string(),
        }
    }

    /// The dashboard's view (`/api/state`), with the actor rows the run state does not carry.
    async fn state(&self) -> serde_json::Value {
        let out = Command::new("curl")
            .args(["-sf", "-m", "5", &format!("{}api/state", self.dashboard)])
            .output()
            .unwrap();
        assert!(out.status.success(), "GET /api/state: {}", out.status);
        serde_json::from_slice(&out.stdout).unwrap()
    }
}

/// What the learner double saw.
#[derive(Default)]
struct Seen {
    transitions: Vec<Transition>,
    batches: u64,
    bad_batches: Vec<String>,
}

#[derive(Clone)]
struct LearnerDouble {
    info: v1::RunInfo,
    seen: Arc<Mutex<Seen>>,
    policy: watch::Receiver<Option<v1::PolicyWeights>>,
}

type PolicyStream =
    Pin<Box<dyn tokio_stream::Stream<Item = Result<v1::PolicyWeights, Status>> + Send>>;

#[tonic::async_trait]
impl Learner for LearnerDouble {
    async fn get_run_info(
        &self,
        _: Request<v1::GetRunInfoRequest>,
    ) -> Result<Response<v1::RunInfo>, Status> {
        Ok(Response::new(self.info.clone()))
    }

    async fn push_transitions(
        &self,
        request: Request<Streaming<v1::TransitionBatch>>,
    ) -> Result<Response<v1::PushSummary>, Status> {
        let mut stream = request.into_inner();
        let layout = RecordLayout::new(7, 2);
        let mut accepted = 0;
        while let Some(batch) = stream.message().await? {
            let mut seen = self.seen.lock().unwrap();
            seen.batches += 1;
            match layout.decode_batch(&batch.records) {
                Ok(ts) if ts.len() == batch.count as usize && batch.obs_dim == 7 => {
                    accepted += ts.len() as u64;
                    seen.transitions.extend(ts);
                }
                Ok(ts) => {
                    seen.bad_batches
                        .push(format!("count {} vs {} records", batch.count, ts.len()))
                }
                Err(e) => seen.bad_batches.push(e.to_string()),
            }
        }
        Ok(Response::new(v1::PushSummary {
            accepted,
            dropped_stale_epoch: 0,
        }))
    }

    type WatchPolicyStream = PolicyStream;

    async fn watch_policy(
        &self,
        request: Request<v1::WatchPolicyRequest>,
    ) -> Result<Response<PolicyStream>, Status> {
        let after = request.into_inner().after_version;
        let stream = tokio_stream::StreamExt::filter_map(
            tokio_stream::wrappers::WatchStream::new(self.policy.clone()),
            move |p| p.filter(|p| p.version > after).map(Ok),
        );
        Ok(Response::new(Box::pin(stream)))
    }

    async fn health(
        &self,
        _: Request<v1::HealthRequest>,
    ) -> Result<Response<v1::HealthReply>, Status> {
        Ok(Response::new(v1::HealthReply {
            ok: true,
            ..Default::default()
        }))
    }
}

/// The learner double on a free loopback port, on its own runtime and thread: shutting it down
/// drops that runtime, which cuts every connection as a dead process would.
struct LearnerHandle {
    addr: String,
    seen: Arc<Mutex<Seen>>,
    publish: watch::Sender<Option<v1::PolicyWeights>>,
    stop: Option<std::sync::mpsc::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
    weights: Vec<u8>,
}

impl Drop for LearnerHandle {
    fn drop(&mut self) {
        self.shut_down();
    }
}

impl LearnerHandle {
    async fn start(cfg: &RunConfig, curriculum: &str) -> LearnerHandle {
        Self::start_scaled(cfg, curriculum, Vec::new()).await
    }

    /// A learner double whose run description carries spec 6.4's `action_scale`.
    async fn start_scaled(
        cfg: &RunConfig,
        curriculum: &str,
        action_scale: Vec<f32>,
    ) -> LearnerHandle {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        listener.set_nonblocking(true).unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        let seen = Arc::new(Mutex::new(Seen::default()));
        let (publish, policy) = watch::channel(None);
        let double = LearnerDouble {
            info: v1::RunInfo {
                run_name: cfg.name.clone(),
                env_id: cfg.env.env_id.clone(),
                obs_dim: 7,
                action_dim: 2,
                curriculum_addr: curriculum.to_string(),
                transport: "grpc".into(),
                config_yaml: to_yaml(cfg),
                run_seed: cfg.seed,
                action_scale,
                ..Default::default()
            },
            seen: seen.clone(),
            policy,
        };
        let (stop, stopped) = std::sync::mpsc::channel::<()>();
        let thread = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(1)
                .enable_all()
                .build()
                .unwrap();
            rt.spawn(async move {
                let listener = tokio::net::TcpListener::from_std(listener).unwrap();
                tonic::transport::Server::builder()
                    .add_service(InterceptedService::new(
                        LearnerServer::new(double),
                        Guard::new(&test_token()),
                    ))
                    .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener))
                    .await
            });
            let _ = stopped.recv();
            rt.shutdown_background();
        });
        let shape = rfcl_policy::PolicyShape::from_config(cfg, 7, 2);
        let weights = rfcl_policy::PolicyNet::init(shape, 3)
            .unwrap()
            .to_safetensors()
            .unwrap();
        LearnerHandle {
            addr: format!("http://{addr}"),
            seen,
            publish,
            stop: Some(stop),
            thread: Some(thread),
            weights,
        }
    }

    fn publish(&self, version: u64, env_steps: u64) {
        self.publish.send_replace(Some(v1::PolicyWeights {
            version,
            safetensors: self.weights.clone().into(),
            learner_env_steps: env_steps,
        }));
    }

    fn transitions(&self) -> usize {
        self.seen.lock().unwrap().transitions.len()
    }

    fn shut_down(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(thread) = self.thread.take() {
            thread.join().unwrap();
        }
    }
}

fn start_actor(learner: &str, extra: &[&str]) -> ChildGuard {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_actor"));
    child::with_token(&mut cmd, TEST_TOKEN)
        .args(["--connect", learner, "--retry-for", "3"])
        .args(extra)
        .env("RUST_LOG", "info")
        .stdout(Stdio::null());
    ChildGuard::spawn("actor", &mut cmd)
}

/// Waits (polling) until `done` or the deadline; false on timeout.
async fn wait_until(limit: Duration, mut done: impl FnMut() -> bool) -> bool {
    let until = Instant::now() + limit;
    while Instant::now() < until {
        if done() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    done()
}

/// Waits for the actor to exit within `limit`: its exit status and all its stderr.
fn exit_within(mut actor: ChildGuard, limit: Duration) -> (ExitStatus, String) {
    let status = actor.wait_within(limit);
    (status, actor.stderr_text())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_train_actor_explores_then_follows_the_policy_and_reports_every_episode() {
    let dir = tempfile::tempdir().unwrap();
    let (config, demos, cfg) = write_run(dir.path(), "");
    let server = Server::start(&config, &demos, &dir.path().join("run"));
    let mut learner = LearnerHandle::start(&cfg, &server.grpc).await;
    let actor = start_actor(&learner.addr, &["--envs", "3", "--id", "4"]);

    // Uniform exploration first (no policy yet), then a policy below the seed steps: still uniform.
    assert!(wait_until(Duration::from_secs(20), || learner.transitions() >= 64).await);
    learner.publish(1, 100);
    let first_v1 = wait_until(Duration::from_secs(10), || {
        learner
            .seen
            .lock()
            .unwrap()
            .transitions
            .iter()
            .any(|t| t.policy_version == 1)
    })
    .await;
    assert!(first_v1, "transitions carry the held policy's version");
    // Past the seed steps the policy acts.
    learner.publish(2, 250);
    let seen_v2 = wait_until(Duration::from_secs(10), || {
        learner
            .seen
            .lock()
            .unwrap()
            .transitions
            .iter()
            .filter(|t| t.policy_version == 2)
            .count()
            >= 64
    })
    .await;
    assert!(seen_v2);
    let state = server.state().await;

    {
        let seen = learner.seen.lock().unwrap();
        assert!(seen.bad_batches.is_empty(), "{:?}", seen.bad_batches);
        assert!(seen.batches > 0);
        for t in &seen.transitions {
            assert_eq!((t.actor_id, t.stage_epoch, t.mask), (4, 0, 1.0));
            assert!(t.reward == 0.0 || t.reward == 1.0);
            assert!(t.action.iter().all(|a| (-1.0..=1.0).contains(a)));
            assert!(t.obs.iter().chain(&t.next_obs).all(|v| v.is_finite()));
        }
        // Before any policy, the actor explored uniformly (version 0).
        let v0 = seen
            .transitions
            .iter()
            .filter(|t| t.policy_version == 0)
            .count();
        assert!(v0 >= 64, "uniform exploration before any policy: {v0}");
        // Within an episode, next_obs chains into the following obs of the same env.
        let consecutive = seen
            .transitions
            .windows(4)
            .filter(|w| w[0].next_obs == w[3].obs)
            .count();
        assert!(
            consecutive > seen.transitions.len() / 2,
            "3 envs in lockstep"
        );
    }
    // Every finished episode was reported: the curriculum counted episodes and their env steps,
    // and knows the actor.
    let episodes = state["episodes"].as_u64().unwrap();
    let steps = state["env_steps"].as_u64().unwrap();
    assert!(episodes >= 3, "{state}");
    assert!(steps as usize <= learner.transitions() + 3 * 300);
    let actor_row = state["actors"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["actor_id"] == 4)
        .expect("the actor is on the dashboard");
    assert!(actor_row["env_steps"].as_u64().unwrap() > 0);

    // The learner goes away: the actor retries for --retry-for (3 s), then exits non-zero.
    learner.shut_down();
    let (status, stderr) = exit_within(actor, Duration::from_secs(30));
    assert!(!status.success(), "{stderr}");
    assert!(
        stderr.contains("error: actor 4:") && stderr.contains("learner at http://127.0.0.1"),
        "{stderr}"
    );
    assert!(
        stderr.contains("retrying"),
        "the outage is logged: {stderr}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_with_its_streams_open_stops_the_actor_in_seconds() {
    let dir = tempfile::tempdir().unwrap();
    let (config, demos, cfg) = write_run(dir.path(), "");
    let server = Server::start(&config, &demos, &dir.path().join("run"));
    let learner = LearnerHandle::start(&cfg, &server.grpc).await;
    let actor = start_actor(&learner.addr, &["--envs", "2", "--id", "5"]);
    // Streaming transitions, and holding a policy from its WatchPolicy stream.
    assert!(wait_until(Duration::from_secs(20), || learner.transitions() >= 64).await);
    learner.publish(1, 100);
    let has_policy = wait_until(Duration::from_secs(10), || {
        let seen = learner.seen.lock().unwrap();
        seen.transitions.iter().any(|t| t.policy_version == 1)
    })
    .await;
    assert!(has_policy);

    actor.signal(child::Signal::TERM);
    let (status, stderr) = exit_within(actor, Duration::from_secs(10));
    assert!(status.success(), "{stderr}");
    assert!(stderr.contains("stopped"), "{stderr}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_eval_actor_evaluates_each_eval_point_with_the_deterministic_policy() {
    let dir = tempfile::tempdir().unwrap();
    let (config, demos, cfg) = write_run(dir.path(), "  num_eval_actors: 1\n");
    // 2 eval envs × 1000 steps / horizon 300 = 6 episodes per evaluation, raised to 10.
    assert_eq!(rfcl_actor::eval::episodes_per_eval(&cfg), 10);
    let server = Server::start(&config, &demos, &dir.path().join("run"));
    let mut learner = LearnerHandle::start(&cfg, &server.grpc).await;
    let actor = start_actor(&learner.addr, &["--eval", "--envs", "2", "--id", "9"]);

    // Below the seed steps and before the first multiple of eval_freq: nothing to evaluate.
    learner.publish(1, 150);
    tokio::time::sleep(Duration::from_millis(500)).await;
    learner.publish(2, 1100);
    let evals = |state: &serde_json::Value| state["evals"].as_array().unwrap().clone();
    let mut done = false;
    for _ in 0..200 {
        let state = server.state().await;
        if evals(&state)
            .iter()
            .any(|e| e["policy_version"] == 2 && e["episodes"] == 10)
        {
            done = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(done, "{}", server.state().await);
    // The same eval point again: no new evaluation; the next multiple: one more.
    learner.publish(3, 1900);
    tokio::time::sleep(Duration::from_millis(500)).await;
    learner.publish(4, 2050);
    let mut done = false;
    for _ in 0..200 {
        let e = evals(&server.state().await);
        if e.iter()
            .any(|e| e["policy_version"] == 4 && e["episodes"] == 10)
        {
            done = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(done);
    let state = server.state().await;
    let versions: Vec<u64> = evals(&state)
        .iter()
        .map(|e| e["policy_version"].as_u64().unwrap())
        .collect();
    assert_eq!(versions, [2, 4], "{state}");
    for e in evals(&state) {
        let env_steps = e["env_steps"].as_u64().unwrap();
        assert!(env_steps == 1100 || env_steps == 2050, "{e}");
    }
    // Eval episodes are not training data: no transitions, no train episodes.
    assert_eq!(learner.transitions(), 0);
    assert_eq!(state["episodes"], 0);

    // The curriculum server goes away: a clear error naming it.
    drop(server);
    learner.publish(5, 3100);
    let (status, stderr) = exit_within(actor, Duration::from_secs(30));
    assert!(!status.success());
    assert!(
        stderr.contains("curriculum server at http://127.0.0.1") && stderr.contains("unreachable"),
        "{stderr}"
    );
    learner.shut_down();
}

/// Spec 6.4 through the actor binary: PointMaze's reported velocity is `MAX_SPEED` × the env
/// action (0 on a blocked axis), so each transition shows the env action the actor sent.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scaled_run_steps_the_env_with_a_over_s_and_streams_agent_actions() {
    use rfcl_actor::pointmaze::MAX_SPEED;
    let dir = tempfile::tempdir().unwrap();
    let (config, demos, mut cfg) = write_run(dir.path(), "");
    cfg.train.data_action_scale = Some(1.25);
    let server = Server::start(&config, &demos, &dir.path().join("run"));
    // s_0 = 2 halves env actions; s_1 = 0.5 doubles them, clipped to [-1, 1].
    let scale = [2.0f32, 0.5];
    let mut learner = LearnerHandle::start_scaled(&cfg, &server.grpc, scale.to_vec()).await;
    let mut actor = start_actor(&learner.addr, &["--envs", "2", "--id", "1"]);
    assert!(wait_until(Duration::from_secs(20), || learner.transitions() >= 64).await);
    let _ = actor.kill();
    let _ = actor.wait();
    let seen = learner.seen.lock().unwrap();
    assert!(seen.bad_batches.is_empty(), "{:?}", seen.bad_batches);
    let mut moved = [0usize; 2];
    for t in &seen.transitions {
        for d in 0..2 {
            // Agent units, as the learner trains on them.
            assert!((-1.0..=1.0).contains(&t.action[d]), "{t:?}");
            let env = (t.action[d] / scale[d]).clamp(-1.0, 1.0);
            let vel = t.next_obs[2 + d];
            assert!(
                vel == 0.0 || (vel - MAX_SPEED * env).abs() < 1e-5,
                "dim {d}: agent {} -> velocity {vel}, expected {}",
                t.action[d],
                MAX_SPEED * env
            );
            moved[d] += usize::from(vel != 0.0);
        }
    }
    let n = seen.transitions.len();
    assert!(moved.iter().all(|&m| m > n / 2), "{moved:?} of {n}");
    drop(seen);
    learner.shut_down();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_malformed_or_missing_action_scale_is_refused_at_start() {
    let dir = tempfile::tempdir().unwrap();
    let (_, _, mut cfg) = write_run(dir.path(), "");
    cfg.train.data_action_scale = Some(1.25);
    for (scale, expected) in [
        (
            vec![1.0, 1.0, 1.0],
            "malformed RunInfo.action_scale: expected 2 values",
        ),
        (
            vec![1.0, 0.0],
            "malformed RunInfo.action_scale: expected finite values > 0",
        ),
        (vec![], "sent no RunInfo.action_scale"),
    ] {
        let mut learner = LearnerHandle::start_scaled(&cfg, "127.0.0.1:1", scale).await;
        let (status, stderr) = exit_within(
            start_actor(&learner.addr, &["--envs", "1"]),
            Duration::from_secs(20),
        );
        assert!(!status.success());
        assert!(stderr.contains(expected), "{expected:?} in {stderr}");
        learner.shut_down();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unsupported_suite_is_refused_at_start() {
    let dir = tempfile::tempdir().unwrap();
    let (_, _, mut cfg) = write_run(dir.path(), "");
    cfg.env.suite = rfcl_core::config::Suite::Metaworld;
    cfg.env.env_id = "reach-v2-goal-observable".into();
    let mut learner = LearnerHandle::start(&cfg, "127.0.0.1:1").await;
    let (status, stderr) = exit_within(
        start_actor(&learner.addr, &["--envs", "1"]),
        Duration::from_secs(20),
    );
    assert!(!status.success());
    assert!(
        // The Python worker refuses a MetaWorld v2 id (MetaWorld 3 names tasks -v3).
        stderr.contains("env 'reach-v2-goal-observable' of suite 'metaworld': "),
        "{stderr}"
    );
    learner.shut_down();
}

#[test]
fn no_learner_is_a_clear_error_after_the_retry_period() {
    let started = Instant::now();
    // Nothing listens on port 1.
    let (status, stderr) = exit_within(
        start_actor("http://127.0.0.1:1", &[]),
        Duration::from_secs(30),
    );
    assert!(!status.success());
    assert!(
        stderr.contains("learner at http://127.0.0.1:1 unreachable for 3 s (GetRunInfo)"),
        "{stderr}"
    );
    assert!(started.elapsed() >= Duration::from_secs(3));
}
