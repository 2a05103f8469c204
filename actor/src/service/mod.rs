//! The actor service as a library: [`serve`] connects to the learner, makes the envs and runs the
//! train or eval loop, the thin shell that feeds leases and policies into a [`Rollout`] and ships
//! what it produces (transition batches to the learner, episode reports to the curriculum server),
//! until its shutdown future resolves. The `actor` binary parses flags and calls it.
//!
//! * `links`: the learner and curriculum clients, retried with backoff.
//! * [`shm`]: the transport choice and the shared-memory side.
mod links;
pub mod shm;

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::eval::{episodes_per_eval_actor, EvalSchedule};
use crate::net::{policy_from_weights, published_policy_bytes};
use crate::policy::PolicyHandle;
use crate::rollout::{derive_seed, Rollout, RolloutError, RolloutSettings, StepOutput};
use crate::suite::make_env;
use crate::video::{encode_gif, Recorder};
use anyhow::{bail, Context, Result};
use rfcl_core::config::RunConfig;
use rfcl_core::lease::{AcquireRequest, EpisodeReport, ResetLease};
use rfcl_core::transition::{RecordLayout, Transition};
use rfcl_core::video::{EvalVideo, VideoMeta};
use rfcl_proto::auth::ClientAuth;
use rfcl_proto::v1;
use tokio::sync::{mpsc, watch};

use links::{Curriculum, Learner, PushCounters, Reported};
use shm::{Choice, Plan, ShmLink};

/// What the actor was asked to do.
#[derive(Debug, Clone)]
pub struct Options {
    pub connect: String,
    /// The curriculum server's address when it is not the one the learner announces (an actor
    /// on another host reaches it by another name).
    pub curriculum: Option<String>,
    pub auth: ClientAuth,
    pub eval: bool,
    pub envs: u32,
    pub id: u32,
    pub retry_for: Duration,
    pub transport: Choice,
}

/// Why the actor stopped without an error.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stopped {
    /// SIGINT / SIGTERM.
    Signal,
    /// The curriculum server hands out no more leases (stage 1 only, spec 2.7).
    CurriculumFinished,
}

/// The run as the learner describes it, with the env resolved.
struct Run {
    cfg: RunConfig,
    obs_dim: usize,
    action_dim: usize,
    run_seed: u64,
    curriculum: Curriculum,
}

/// Connects, then runs the train or eval loop until `shutdown` resolves or an error.
pub async fn serve(
    opts: Options,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<Stopped> {
    if opts.envs == 0 {
        bail!("--envs must be at least 1");
    }
    let learner = Learner::new(&opts.connect, &opts.auth, opts.retry_for)?;
    let info = learner.run_info(opts.id).await?;
    let cfg = parse_config(&info.config_yaml)
        .with_context(|| format!("the run config sent by the {}", learner.peer))?;
    // Spec 6.4: the learner computed s from the demos; the envs get a / s.
    let action_scale = rfcl_proto::convert::action_scale(&info)
        .with_context(|| format!("the run description sent by the {}", learner.peer))?;
    match (cfg.train.data_action_scale, &action_scale) {
        (Some(_), None) => bail!(
            "the run sets train.data_action_scale (docs/ALGORITHM.md 6.4) but the {} sent no \
             RunInfo.action_scale (a learner older than this actor?)",
            learner.peer
        ),
        (None, Some(_)) => bail!(
            "the {} sent RunInfo.action_scale but the run does not set train.data_action_scale",
            learner.peer
        ),
        _ => {}
    }
    if cfg.env.env_id != info.env_id {
        bail!(
            "the {} runs env '{}' but its config says '{}'",
            learner.peer,
            info.env_id,
            cfg.env.env_id
        );
    }
    let policy_bytes =
        published_policy_bytes(&cfg, info.obs_dim as usize, info.action_dim as usize)
            .context("sizing the run's policy")?;
    let learner = learner.expect_policies_of(policy_bytes);
    let curriculum_addr = opts
        .curriculum
        .clone()
        .unwrap_or_else(|| info.curriculum_addr.clone());
    let run = Run {
        obs_dim: info.obs_dim as usize,
        action_dim: info.action_dim as usize,
        run_seed: info.run_seed,
        curriculum: Curriculum::new(&curriculum_addr, &opts.auth, opts.retry_for)?,
        cfg,
    };
    // An eval actor that records videos renders in its first env only.
    let video_size =
        (opts.eval && run.cfg.eval_env.video_every > 0).then_some(run.cfg.eval_env.video_size);
    let envs = (0..opts.envs)
        .map(|i| {
            make_env(
                &run.cfg.env,
                derive_seed(run.run_seed, opts.id, i),
                run.obs_dim,
                run.action_dim,
                video_size.filter(|_| i == 0),
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    let rollout = Rollout::new(
        envs,
        run.run_seed,
        RolloutSettings {
            actor_id: opts.id,
            num_seed_steps: run.cfg.sac.num_seed_steps,
            deterministic: opts.eval,
        },
    )
    .with_action_scale(action_scale)?;
    tracing::info!(
        actor = opts.id,
        eval = opts.eval,
        envs = opts.envs,
        env = %info.env_id,
        run = %info.run_name,
        action_scale = ?rollout.action_scale(),
        "connected to the {} and the curriculum server at {}",
        learner.peer,
        curriculum_addr
    );

    let layout = RecordLayout::new(run.obs_dim, run.action_dim);
    let batch = run.cfg.service.transition_batch.max(1) as usize;
    let link = open_transport(&opts, &info, batch, layout.record_bytes())?;

    let (policy_tx, policy_rx) = watch::channel(None);
    // Stops the shared-memory threads (if any) when this function returns.
    let stop = StopOnDrop(Arc::new(AtomicBool::new(false)));
    let (watcher, publisher): (Pin<Box<dyn Future<Output = Result<()>>>>, _) = match link {
        Some(link) => {
            let (publisher, policy) = link.into_parts();
            shm::start_policy_follower(policy, policy_tx, stop.0.clone())?;
            // Nothing else would notice a dead learner: check it is there.
            let learner = learner.clone();
            let run_id = info.run_id.clone();
            (
                Box::pin(async move { learner.watch_alive(Duration::from_secs(2), &run_id).await }),
                Some(publisher),
            )
        }
        None => {
            let learner = learner.clone();
            (
                Box::pin(async move { learner.watch_policy(policy_tx).await }),
                None,
            )
        }
    };
    let transport = if publisher.is_some() { "shm" } else { "grpc" };
    let mut watcher = watcher;
    tokio::pin!(shutdown);
    if opts.eval {
        // Eval actors send no transitions.
        drop(publisher);
        let work = eval_loop(&run, rollout, policy_rx);
        let stopped = tokio::select! {
            r = work => r,
            r = &mut watcher => Err(r.err().unwrap_or_else(|| anyhow::anyhow!("the policy watch ended"))),
            _ = &mut shutdown => Ok(Stopped::Signal),
        };
        unless_finished(&run, stopped).await
    } else {
        let counters = Arc::new(PushCounters::default());
        // Small: with the push stream's acknowledged windows, this bounds how far the actor runs
        // ahead of the learner (policy lag).
        let capacity = 1;
        let (batch_tx, batch_rx) = mpsc::channel(capacity);
        let pusher = match publisher {
            Some(publisher) => {
                let (done, stop_send) =
                    shm::start_pusher(publisher, batch_rx, counters.clone(), opts.retry_for)?;
                Pusher::Shm { done, stop_send }
            }
            None => {
                let learner = learner.clone();
                let counters = counters.clone();
                Pusher::Grpc(tokio::spawn(async move {
                    learner.push_transitions(batch_rx, counters).await
                }))
            }
        };
        let mut train = TrainLoop {
            run: &run,
            rollout,
            policy_rx,
            batch_tx,
            pending: Vec::new(),
            layout,
            batch,
            refused: 0,
            policy: None,
        };
        let stopped = {
            let work = train.run();
            tokio::pin!(work);
            tokio::select! {
                r = &mut work => r,
                r = &mut watcher => Err(r.err().unwrap_or_else(|| anyhow::anyhow!("the policy watch ended"))),
                _ = &mut shutdown => Ok(Stopped::Signal),
            }
        };
        let stopped = unless_finished(&run, stopped).await;
        // Flush what is ready (best effort, bounded) and account for the rest.
        let unsent = train.pending.len();
        drop(train.batch_tx);
        let flushed = pusher.finish(stopped.is_ok()).await;
        tracing::info!(
            transport,
            env_steps = train.rollout.env_steps(),
            episodes = train.rollout.episodes(),
            sent = counters.sent.load(Ordering::Relaxed),
            accepted = counters.accepted.load(Ordering::Relaxed),
            unconfirmed = counters.unconfirmed.load(Ordering::Relaxed),
            dropped_stale_epoch = counters.dropped_stale_epoch.load(Ordering::Relaxed),
            given_up = counters.given_up.load(Ordering::Relaxed),
            unsent_partial_batch = unsent,
            abandoned_episodes = train.rollout.abandoned(),
            sim_restarts = train.rollout.sim_restarts(),
            refused_reports = train.refused,
            flushed,
            "actor stopping"
        );
        stopped
    }
}

/// An error that came from losing the learner is the run's normal end when the curriculum
/// server (still up) says the run is finished: the learner stops once the run is over.
async fn unless_finished(run: &Run, stopped: Result<Stopped>) -> Result<Stopped> {
    match stopped {
        Err(e) if run.curriculum.finished().await => {
            tracing::info!("the run is finished (the curriculum server says so): {e:#}");
            Ok(Stopped::CurriculumFinished)
        }
        other => other,
    }
}

/// Sets its flag when dropped: the shared-memory threads watch it.
struct StopOnDrop(Arc<AtomicBool>);

impl Drop for StopOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

/// The shared-memory link when [`shm::decide`] and opening the services say so; `None` for gRPC.
/// Logs the choice and why.
fn open_transport(
    opts: &Options,
    info: &v1::RunInfo,
    batch: usize,
    record_bytes: usize,
) -> Result<Option<ShmLink>> {
    let own_host = rfcl_shm::host_identity();
    match shm::decide(opts.transport, info, &own_host)? {
        Plan::Grpc { why } => {
            tracing::info!(
                actor = opts.id,
                transport = "grpc",
                "transport: gRPC ({why})"
            );
            Ok(None)
        }
        Plan::Shm { required } => match ShmLink::open(info, opts.id, batch, record_bytes) {
            Ok(link) => {
                let (transitions, policy) = link.services();
                tracing::info!(
                    actor = opts.id,
                    transport = "shm",
                    %transitions,
                    %policy,
                    "transport: shared memory (iceoryx2; {})",
                    if required { "--transport shm" } else { "on the learner's host" }
                );
                Ok(Some(link))
            }
            Err(e) if required => Err(e).context("--transport shm"),
            Err(e) => {
                tracing::warn!(
                    actor = opts.id,
                    transport = "grpc",
                    "transport: gRPC (on the learner's host, but shared memory failed: {e:#})"
                );
                Ok(None)
            }
        },
    }
}

/// Where the train loop's batches go.
enum Pusher {
    Grpc(tokio::task::JoinHandle<Result<()>>),
    Shm {
        done: tokio::sync::oneshot::Receiver<Result<()>>,
        /// Ends a send that waits for room in the learner's queue.
        stop_send: Arc<AtomicBool>,
    },
}

impl Pusher {
    /// After the batch channel closed: waits (at most 3 s) for what is queued to go out when the
    /// actor stopped cleanly; otherwise abandons it (counted by the pusher). Whether it flushed.
    async fn finish(self, clean: bool) -> bool {
        let limit = Duration::from_secs(if clean { 3 } else { 0 });
        match self {
            Pusher::Grpc(task) => {
                if !clean {
                    task.abort();
                    return false;
                }
                tokio::time::timeout(limit, task).await.is_ok()
            }
            Pusher::Shm { done, stop_send } => {
                let flushed = clean && tokio::time::timeout(limit, done).await.is_ok();
                stop_send.store(true, Ordering::Relaxed);
                flushed
            }
        }
    }
}

/// The resolved run config the learner sends (`to_yaml` output), validated.
fn parse_config(yaml: &str) -> Result<RunConfig> {
    if yaml.trim().is_empty() {
        bail!("it is empty");
    }
    let cfg: RunConfig = serde_saphyr::from_str(yaml).context("it is not a valid run config")?;
    cfg.validate()?;
    Ok(cfg)
}

/// Brings `current` to the newest published policy: new weights are loaded in place (the network
/// is built once, from the run's config and dims).
fn refresh_policy(
    rx: &mut watch::Receiver<Option<Arc<v1::PolicyWeights>>>,
    run: &Run,
    current: &mut Option<PolicyHandle>,
) -> Result<()> {
    let Some(weights) = rx.borrow_and_update().clone() else {
        return Ok(());
    };
    let context = || format!("loading policy version {}", weights.version);
    match current {
        Some(handle) => {
            handle
                .policy
                .load(&weights.safetensors)
                .map_err(|e| anyhow::anyhow!(e))
                .with_context(context)?;
            handle.version = weights.version;
            handle.env_steps = weights.learner_env_steps;
        }
        None => {
            let policy =
                policy_from_weights(&weights.safetensors, &run.cfg, run.obs_dim, run.action_dim)
                    .with_context(context)?;
            *current = Some(PolicyHandle {
                version: weights.version,
                env_steps: weights.learner_env_steps,
                policy,
            });
        }
    }
    Ok(())
}

struct TrainLoop<'a> {
    run: &'a Run,
    rollout: Rollout,
    policy_rx: watch::Receiver<Option<Arc<v1::PolicyWeights>>>,
    batch_tx: mpsc::Sender<v1::TransitionBatch>,
    pending: Vec<Transition>,
    layout: RecordLayout,
    batch: usize,
    refused: u64,
    policy: Option<PolicyHandle>,
}

impl TrainLoop<'_> {
    /// Acquire leases for idle envs, step all envs, ship transitions in batches, report episodes.
    async fn run(&mut self) -> Result<Stopped> {
        let actor_id = self.rollout.settings().actor_id;
        let mut out = StepOutput::default();
        let mut last_log = Instant::now();
        loop {
            if self.policy_rx.has_changed().unwrap_or(false) {
                refresh_policy(&mut self.policy_rx, self.run, &mut self.policy)?;
            }
            for env in self.rollout.idle_envs() {
                let req = AcquireRequest {
                    actor_id,
                    env_index: env as u32,
                    eval: false,
                };
                let Some(lease) = self.run.curriculum.acquire(req).await? else {
                    return Ok(Stopped::CurriculumFinished);
                };
                self.start(env, lease).await?;
            }
            out.clear();
            self.rollout.step(self.policy.as_mut(), &mut out)?;
            self.pending.append(&mut out.transitions);
            while self.pending.len() >= self.batch {
                let batch: Vec<Transition> = self.pending.drain(..self.batch).collect();
                self.send(&batch).await?;
            }
            for (env, report) in out.finished.drain(..) {
                self.report_and_continue(env, &report).await?;
            }
            if last_log.elapsed() > Duration::from_secs(30) {
                last_log = Instant::now();
                tracing::info!(
                    env_steps = self.rollout.env_steps(),
                    episodes = self.rollout.episodes(),
                    policy_version = self.policy.as_ref().map(|p| p.version),
                    "actor progress"
                );
            }
            // Let the connection tasks run between lockstep iterations.
            tokio::task::yield_now().await;
        }
    }

    async fn send(&mut self, transitions: &[Transition]) -> Result<()> {
        let mut records = vec![0u8; transitions.len() * self.layout.record_bytes()];
        self.layout
            .encode_batch(transitions, &mut records)
            .context("encoding a transition batch")?;
        let batch = v1::TransitionBatch {
            actor_id: self.rollout.settings().actor_id,
            obs_dim: self.layout.obs_dim as u32,
            action_dim: self.layout.action_dim as u32,
            count: transitions.len() as u32,
            records,
        };
        self.batch_tx
            .send(batch)
            .await
            .map_err(|_| anyhow::anyhow!("the transition stream to the learner has stopped"))
    }

    /// Reports a finished episode and starts env `env`'s next one in the same round trip (a
    /// refused report leaves the env idle: the next iteration acquires a lease for it).
    async fn report_and_continue(&mut self, env: usize, report: &EpisodeReport) -> Result<()> {
        let next = AcquireRequest {
            actor_id: report.actor_id,
            env_index: env as u32,
            eval: false,
        };
        let (reported, lease) = self.run.curriculum.report_and_acquire(report, next).await?;
        self.acknowledged(reported, report.lease_id);
        if let Some(lease) = lease {
            self.start(env, lease).await?;
        }
        Ok(())
    }

    fn acknowledged(&mut self, reported: Reported, lease_id: u64) {
        match reported {
            Reported::Acked { stage_epoch, .. } => {
                let dropped = self.rollout.abandon_epochs_before(stage_epoch);
                if dropped > 0 {
                    tracing::info!(
                        stage_epoch,
                        dropped,
                        "new stage epoch: dropped unfinished episodes of the old one"
                    );
                }
            }
            Reported::Refused(why) => {
                self.refused += 1;
                tracing::warn!(lease = lease_id, "report refused: {why}");
            }
        }
    }

    /// Starts `lease` in env `env`. A lease whose state the env refuses (a bad demo state) is
    /// reported as failed with the reason, and the next lease taken in the same round trip: the
    /// curriculum server counts it against its demo and the run goes on. Only an env that fails
    /// [`MAX_RESET_FAILURES_IN_A_ROW`] resets in a row, whatever the state, ends the actor.
    async fn start(&mut self, env: usize, mut lease: ResetLease) -> Result<()> {
        loop {
            let (lease_id, stage_epoch, error) = match self.rollout.begin(env, lease) {
                Ok(()) => return Ok(()),
                Err(RolloutError::Reset {
                    lease_id,
                    stage_epoch,
                    error,
                    ..
                }) if self.rollout.reset_failures_in_a_row() < MAX_RESET_FAILURES_IN_A_ROW => {
                    (lease_id, stage_epoch, error)
                }
                Err(e) => {
                    return Err(e).with_context(|| {
                        format!(
                            "{} resets in a row failed: the env cannot reset at all",
                            self.rollout.reset_failures_in_a_row()
                        )
                    })
                }
            };
            tracing::warn!(
                lease = lease_id,
                "could not reset env {env} to the lease's state, reporting it as failed: {error}"
            );
            let report = self
                .rollout
                .reset_failure_report(lease_id, stage_epoch, &error);
            let next = AcquireRequest {
                actor_id: report.actor_id,
                env_index: env as u32,
                eval: false,
            };
            let (reported, next) = self
                .run
                .curriculum
                .report_and_acquire(&report, next)
                .await?;
            self.acknowledged(reported, lease_id);
            match next {
                Some(next) => lease = next,
                None => return Ok(()),
            }
        }
    }
}

/// Resets that may fail in a row before the actor gives up on its env: a bad demo state fails
/// one lease, an env that cannot reset fails them all.
const MAX_RESET_FAILURES_IN_A_ROW: u32 = 8;

/// Waits for policies; evaluates the ones that pass a multiple of `eval_freq` (spec 5.7).
async fn eval_loop(
    run: &Run,
    mut rollout: Rollout,
    mut policy_rx: watch::Receiver<Option<Arc<v1::PolicyWeights>>>,
) -> Result<Stopped> {
    let mut schedule = EvalSchedule::from_config(&run.cfg);
    // A resumed run, or this actor restarted: the points already evaluated are not evaluated again.
    match run.curriculum.last_complete_eval().await {
        Ok(env_steps) => schedule.go_on_after(env_steps),
        Err(e) => tracing::warn!(
            "{e:#}; evaluating from the first policy past a multiple of sac.eval_freq on"
        ),
    }
    let episodes = episodes_per_eval_actor(&run.cfg);
    let actor_id = rollout.settings().actor_id;
    let mut out = StepOutput::default();
    let mut current: Option<PolicyHandle> = None;
    let mut videos = EvalVideos::new(run.cfg.eval_env.video_every);
    loop {
        if policy_rx.changed().await.is_err() {
            bail!("the policy watch ended");
        }
        let Some(steps) = policy_rx.borrow().as_ref().map(|w| w.learner_env_steps) else {
            continue;
        };
        let skipped_before = schedule.skipped();
        if !schedule.due(steps) {
            continue;
        }
        if schedule.skipped() > skipped_before {
            tracing::warn!(
                skipped = schedule.skipped() - skipped_before,
                total_skipped = schedule.skipped(),
                "the learner passed several eval points during one evaluation: evaluating the newest"
            );
        }
        refresh_policy(&mut policy_rx, run, &mut current)?;
        let Some(policy) = current.as_mut() else {
            continue;
        };
        let started_at = Instant::now();
        let (mut started, mut finished, mut successes, mut refused) = (0u64, 0u64, 0u64, 0u64);
        videos.evaluation_begins();
        while finished < episodes {
            for env in rollout.idle_envs() {
                if started == episodes {
                    break;
                }
                let req = AcquireRequest {
                    actor_id,
                    env_index: env as u32,
                    eval: true,
                };
                let Some(lease) = run.curriculum.acquire(req).await? else {
                    return Ok(Stopped::CurriculumFinished);
                };
                let seed = lease.reset.seed;
                rollout.begin(env, lease)?;
                videos.begun(&mut rollout, env, seed);
                started += 1;
            }
            out.clear();
            rollout.step(Some(&mut *policy), &mut out)?;
            videos.stepped(&mut rollout, &out);
            for (env, report) in out.finished.drain(..) {
                videos.finished(env, &report, &run.curriculum).await;
                finished += 1;
                successes += u64::from(report.success_at_end);
                let (reported, lease) = if started < episodes {
                    let next = AcquireRequest {
                        actor_id,
                        env_index: env as u32,
                        eval: true,
                    };
                    run.curriculum.report_and_acquire(&report, next).await?
                } else {
                    (run.curriculum.report(&report).await?, None)
                };
                if let Reported::Refused(why) = reported {
                    refused += 1;
                    tracing::warn!(lease = report.lease_id, "eval report refused: {why}");
                }
                if let Some(lease) = lease {
                    let seed = lease.reset.seed;
                    rollout.begin(env, lease)?;
                    videos.begun(&mut rollout, env, seed);
                    started += 1;
                }
            }
            tokio::task::yield_now().await;
        }
        tracing::info!(
            policy_version = policy.version,
            env_steps = policy.env_steps,
            episodes,
            success_at_end = successes as f64 / episodes as f64,
            refused,
            seconds = started_at.elapsed().as_secs_f64(),
            videos_sent = videos.sent,
            videos_failed = videos.failed,
            "evaluation done"
        );
    }
}

/// Records the first episode of env 0 in every `eval_env.video_every`-th evaluation and sends it
/// to the curriculum server. A video that cannot be made or sent is logged and counted, never a
/// reason to stop evaluating.
struct EvalVideos {
    every: u32,
    evaluations: u64,
    /// Whether this evaluation still wants its video.
    wanted: bool,
    recording: Option<(Recorder, u64)>,
    sent: u64,
    failed: u64,
}

impl EvalVideos {
    fn new(every: u32) -> Self {
        EvalVideos {
            every,
            evaluations: 0,
            wanted: false,
            recording: None,
            sent: 0,
            failed: 0,
        }
    }

    fn evaluation_begins(&mut self) {
        self.wanted = self.every > 0 && self.evaluations.is_multiple_of(u64::from(self.every));
        self.evaluations += 1;
        self.recording = None;
    }

    fn fail(&mut self, what: &str, e: impl std::fmt::Display) {
        self.failed += 1;
        self.recording = None;
        tracing::warn!(failed = self.failed, "eval video: {what}: {e}");
    }

    fn begun(&mut self, rollout: &mut Rollout, env: usize, seed: Option<u64>) {
        if env != 0 || !self.wanted {
            return;
        }
        self.wanted = false;
        match rollout.render(0) {
            Ok(first) => self.recording = Some((Recorder::new(first), seed.unwrap_or(0))),
            Err(e) => self.fail("rendering the reset state", e),
        }
    }

    fn stepped(&mut self, rollout: &mut Rollout, out: &StepOutput) {
        let Some((rec, _)) = self.recording.as_mut() else {
            return;
        };
        let last = out.finished.iter().any(|(env, _)| *env == 0);
        if rec.step(last) {
            match rollout.render(0) {
                Ok(frame) => rec.push(frame),
                Err(e) => self.fail("rendering a step", e),
            }
        }
    }

    async fn finished(&mut self, env: usize, report: &EpisodeReport, curriculum: &Curriculum) {
        if env != 0 {
            return;
        }
        let Some((rec, seed)) = self.recording.take() else {
            return;
        };
        let gif = match tokio::task::spawn_blocking(move || encode_gif(rec.frames())).await {
            Ok(Ok(gif)) => gif,
            Ok(Err(e)) => return self.fail("encoding", e),
            Err(e) => return self.fail("encoding", e),
        };
        let video = EvalVideo {
            meta: VideoMeta {
                policy_version: report.policy_version,
                env_steps: report.policy_env_steps,
                seed,
                success_at_end: report.success_at_end,
                episode_return: report.episode_return,
                actor_id: report.actor_id,
            },
            gif,
        };
        let bytes = video.gif.len();
        match curriculum.put_video(video).await {
            Ok(name) => {
                self.sent += 1;
                tracing::info!(bytes, "eval video sent: {name}");
            }
            Err(e) => self.fail("sending", format!("{e:#}")),
        }
    }
}
