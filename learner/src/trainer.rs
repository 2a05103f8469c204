//! The training loop: one dedicated thread owns the agent ([`Sac`]) and the [`Replay`], takes
//! validated transition batches from a bounded queue, and runs the SAC schedule of spec 5.2/5.4
//! under the UTD limiter ([`UtdLimiter`]); it applies stage changes (spec 4), publishes a policy
//! version after every iteration, writes metrics and checkpoints.
//!
//! Reading order of one pass of [`Trainer::run`]'s loop:
//! 1. stage events that arrived, the shutdown flag;
//! 2. an iteration the limiter says is due (`sync`: exactly one per K received env steps past the
//!    warm-up; `async`: flat out once past the warm-up);
//! 3. the metrics row, then the checkpoint, when their env-step boundary is reached; a checkpoint
//!    also when `sac.save_every_s` seconds passed since the last one and anything changed (it
//!    writes only the replay's changed segments, so it is cheap enough to take every minute);
//! 4. the budget (`train.steps`);
//! 5. more records: the ingest stops at the next boundary (an iteration due, a metrics row, a
//!    checkpoint, the budget), so each of them happens at an exact env-step count and a resumed
//!    run continues exactly.
//!
//! Records are handled one by one in arrival order: a record of an ended stage epoch is dropped
//! and counted; a record of a newer epoch waits until the curriculum server's announcement of that
//! epoch has been applied (spec 4: online buffer → offline buffer, online emptied, then
//! `sac.num_seed_steps` policy-only steps with no updates; optimiser states and α are kept).
//!
//! Policy versions: version 1 is the initial, untrained policy, published at start (0 means "no
//! policy", so an actor with none asks `WatchPolicy` for versions after 0); every iteration
//! publishes the next version with the env steps received so far, so version v follows v − 1
//! iterations. A resumed learner publishes its restored version first.
//!
//! Divergence: every iteration's losses are checked, and the weights before each publication,
//! checkpoint and export; the first NaN or infinity stops the run with
//! [`TrainError::NonFiniteLoss`] / [`TrainError::NonFiniteWeights`] (the process exits non-zero),
//! so non-finite weights are never published, exported or checkpointed.
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use rfcl_core::config::{RunConfig, UtdMode};
use rfcl_core::demo::DemoSet;
use rfcl_core::transition::RecordLayout;
use rfcl_proto::v1;
use thiserror::Error;
use tokio::sync::{mpsc, watch};

use crate::checkpoint::{self, CheckpointError, Extras, Manifest, Progress};
use crate::error::LearnerError;
use crate::ingest::IngestItem;
use crate::limiter::UtdLimiter;
use crate::metrics::{MetricsCsv, Row, Timings, UpdateMeans};
use crate::policy::{self, PolicyDescription, PolicyError, PolicyShape};
use crate::prom::{self, LearnerMetrics};
use crate::replay::{data_action_scale, offline_from_demos, Replay, ReplayBuffer};
use crate::sac::Sac;
use crate::tensorboard::EventWriter;

/// How often the training thread logs its progress line (stderr).
pub const REPORT_EVERY: Duration = Duration::from_secs(10);

/// Causes are sources, never repeated in the message (see [`crate::error`]).
#[derive(Debug, Error)]
pub enum TrainError {
    #[error(transparent)]
    Learner(#[from] LearnerError),
    #[error("checkpoint")]
    Checkpoint(#[from] CheckpointError),
    #[error("policy")]
    Policy(#[from] PolicyError),
    #[error("{what} {}", path.display())]
    Io {
        what: &'static str,
        path: PathBuf,
        source: std::io::Error,
    },
    /// A loss of an iteration is NaN or infinite: training diverged.
    #[error(
        "training diverged: the {loss} is {value} in the iteration of critic updates {first_update}-{last_update} (env step {env_steps}); stopped before publishing, exporting or checkpointing its weights (lower the learning rates?)"
    )]
    NonFiniteLoss {
        loss: &'static str,
        value: f64,
        first_update: u64,
        last_update: u64,
        env_steps: u64,
    },
    /// Weights hold a NaN or an infinity.
    #[error(
        "training diverged: {tensor} holds NaN or infinite values after critic update {critic_updates} (env step {env_steps}); refusing to {action} them"
    )]
    NonFiniteWeights {
        tensor: String,
        action: &'static str,
        critic_updates: u64,
        env_steps: u64,
    },
}

type Result<T> = std::result::Result<T, TrainError>;

/// What the service reads of the training thread's state (Health, RunInfo).
#[derive(Debug, Default)]
pub struct LearnerStatus {
    /// Written by the training thread at consistent points (after an iteration, when the ingest
    /// pauses), so a reader never sees env steps and updates of different moments.
    snapshot: std::sync::Mutex<StatusSnapshot>,
    /// The training thread stopped with an error.
    pub failed: AtomicBool,
    /// The training thread finished (final checkpoint written).
    pub finished: AtomicBool,
}

/// One consistent reading of the training thread's counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StatusSnapshot {
    pub env_steps: u64,
    pub critic_updates: u64,
    pub policy_version: u64,
    pub stage_epoch: u64,
    pub dropped_stale_epoch: u64,
}

impl LearnerStatus {
    pub fn snapshot(&self) -> StatusSnapshot {
        *self.snapshot.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn set(&self, snapshot: StatusSnapshot) {
        *self.snapshot.lock().unwrap_or_else(|p| p.into_inner()) = snapshot;
    }
}

/// Why the training loop ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopReason {
    /// `train.steps` env steps received.
    Budget,
    /// SIGINT / SIGTERM.
    Signal,
    /// The curriculum server announced the end of the run (`train.stage_1_only`).
    CurriculumFinished,
    /// The ingest queue closed.
    InputsClosed,
}

/// The channels the training thread listens to.
pub struct TrainerInputs {
    pub data: mpsc::Receiver<IngestItem>,
    pub stages: mpsc::UnboundedReceiver<v1::StageEvent>,
    pub shutdown: watch::Receiver<bool>,
    /// The runtime whose timers and channels the thread waits on.
    pub runtime: tokio::runtime::Handle,
}

/// Seeds derived from the run seed: the agent takes the run seed itself (network init, policy
/// noise, target members), the replay sampler this one.
pub fn replay_seed(run_seed: u64) -> u64 {
    run_seed ^ 0x9E37_79B9_7F4A_7C15
}

/// K = `env.num_envs · sac.steps_per_env`, env steps per training iteration (spec 5.2).
pub fn steps_per_iteration(cfg: &RunConfig) -> u64 {
    u64::from(cfg.env.num_envs) * u64::from(cfg.sac.steps_per_env)
}

/// Activity of one window (a metrics row or a progress line).
#[derive(Debug, Clone)]
struct Window {
    start: Instant,
    env_steps: u64,
    critic_updates: u64,
    updates: UpdateMeans,
    timings: Timings,
    lag_max: u64,
}

impl Window {
    fn new(progress: &Progress) -> Self {
        Self {
            start: Instant::now(),
            env_steps: progress.env_steps,
            critic_updates: progress.critic_updates,
            updates: UpdateMeans::default(),
            timings: Timings::default(),
            lag_max: 0,
        }
    }
}

/// The training thread's state (see the module docs).
pub struct Trainer {
    cfg: RunConfig,
    config_yaml: String,
    run_dir: PathBuf,
    env_id: String,
    layout: RecordLayout,
    sac: Sac,
    replay: Replay,
    limiter: UtdLimiter,
    progress: Progress,
    action_scale: Option<Vec<f32>>,
    csv: MetricsCsv,
    /// TensorBoard events: the values of each `metrics.csv` row.
    tb: EventWriter,
    /// Prometheus state (`learner --metrics-port`), refreshed with the Health status.
    prom: Arc<LearnerMetrics>,
    /// Seconds per activity since this process started (Prometheus).
    seconds: Timings,
    /// Critic updates/s, env steps/s and the largest policy lag of the last progress window.
    last_window: (f64, f64, u64),
    /// A batch partly handled (the ingest paused at a boundary).
    pending: Option<IngestItem>,
    stop: Option<StopReason>,
    row: Window,
    report: Window,
    started: Instant,
    wall_ms_at_start: u64,
    policy_tx: watch::Sender<Arc<v1::PolicyWeights>>,
    status: Arc<LearnerStatus>,
    /// Last time a policy-lag warning was logged.
    lag_warned: Option<Instant>,
    /// When the last checkpoint was written (or this process started) and the env steps, critic
    /// updates and stage epoch it held (the wall-time cadence skips a learner with nothing new).
    last_checkpoint: (Instant, (u64, u64, u64)),
}

impl Trainer {
    /// A new run: a fresh agent, the demos as the offline buffer (spec 6.2, with
    /// `data_action_scale`, 6.4; none with `train_on_demo_actions: false`, 6.3), an empty online
    /// buffer, and the stage the curriculum server announced first.
    pub fn fresh(
        cfg: RunConfig,
        demos: &DemoSet,
        run_dir: PathBuf,
        first_stage: &v1::StageEvent,
    ) -> Result<(
        Self,
        watch::Receiver<Arc<v1::PolicyWeights>>,
        Arc<LearnerStatus>,
    )> {
        let (d, a) = (demos.obs_dim, demos.action_dim);
        let sac = Sac::new(d, a, &cfg.sac, &cfg.network, cfg.seed)?;
        let action_scale = action_scale(&cfg, demos)?;
        let offline = if cfg.train.train_on_demo_actions {
            Some(offline_from_demos(&demos.demos, action_scale.as_deref())?)
        } else {
            None
        };
        let online = ReplayBuffer::new("online", cfg.sac.replay_buffer_capacity as usize, d, a)?;
        let replay = Replay::new(online, offline, replay_seed(cfg.seed));
        let limiter = UtdLimiter::new(
            cfg.sac.utd_mode,
            steps_per_iteration(&cfg),
            u64::from(cfg.sac.grad_updates_per_step),
            cfg.sac.num_seed_steps,
        );
        let progress = Progress {
            policy_version: 1,
            stage: first_stage.stage.max(1),
            stage_epoch: first_stage.stage_epoch,
            next_checkpoint_at: cfg.sac.save_freq,
            next_log_at: cfg.sac.log_freq,
            ..Progress::default()
        };
        Self::assemble(
            cfg,
            demos,
            run_dir,
            sac,
            replay,
            limiter,
            progress,
            action_scale,
            None,
        )
    }

    /// Spreads the critic ensemble's members over `threads` threads (see
    /// [`Sac::set_member_threads`]); the maths stay the same.
    pub fn set_member_threads(&mut self, threads: usize) {
        self.sac.set_member_threads(threads);
    }

    /// Continues the run whose checkpoint `manifest` describes: weights, optimiser states,
    /// temperature, RNGs, counters, UTD limiter and both buffers as they were. A backlog of owed
    /// iterations (a changed schedule or mode) is clamped, not burst.
    pub fn resume(
        cfg: RunConfig,
        demos: &DemoSet,
        run_dir: PathBuf,
        manifest: &Manifest,
    ) -> Result<(
        Self,
        watch::Receiver<Arc<v1::PolicyWeights>>,
        Arc<LearnerStatus>,
    )> {
        let (d, a) = (demos.obs_dim, demos.action_dim);
        let mut sac = Sac::new(d, a, &cfg.sac, &cfg.network, cfg.seed)?;
        let replay =
            checkpoint::restore(&checkpoint::checkpoint_dir(&run_dir), manifest, &mut sac)?;
        let mut limiter = manifest.limiter.clone();
        limiter.reconfigure(
            cfg.sac.utd_mode,
            steps_per_iteration(&cfg),
            u64::from(cfg.sac.grad_updates_per_step),
        );
        let forgiven = limiter.clamp_backlog();
        if forgiven > 0 {
            tracing::warn!(
                forgiven,
                "the resumed schedule owed {} iterations: catch-up clamped to 1",
                forgiven + 1
            );
        }
        let action_scale = action_scale(&cfg, demos)?;
        let progress = manifest.progress.clone();
        Self::assemble(
            cfg,
            demos,
            run_dir,
            sac,
            replay,
            limiter,
            progress,
            action_scale,
            Some(manifest.progress.env_steps),
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn assemble(
        cfg: RunConfig,
        demos: &DemoSet,
        run_dir: PathBuf,
        sac: Sac,
        replay: Replay,
        limiter: UtdLimiter,
        progress: Progress,
        action_scale: Option<Vec<f32>>,
        resumed_at: Option<u64>,
    ) -> Result<(
        Self,
        watch::Receiver<Arc<v1::PolicyWeights>>,
        Arc<LearnerStatus>,
    )> {
        let csv_path = run_dir.join("metrics.csv");
        let csv = MetricsCsv::open(&csv_path, resumed_at).map_err(|source| TrainError::Io {
            what: "opening",
            path: csv_path.clone(),
            source,
        })?;
        let tb = EventWriter::create(&run_dir, resumed_at).map_err(|source| TrainError::Io {
            what: "creating a TensorBoard event file in",
            path: run_dir.clone(),
            source,
        })?;
        let layout = RecordLayout::new(sac.obs_dim(), sac.action_dim());
        let config_yaml = rfcl_core::config::to_yaml(&cfg);
        let env_id = demos
            .env_id
            .clone()
            .unwrap_or_else(|| cfg.env.env_id.clone());
        let status = Arc::new(LearnerStatus::default());
        let (policy_tx, policy_rx) = watch::channel(Arc::new(v1::PolicyWeights {
            version: progress.policy_version,
            safetensors: policy::encode_actor(&sac)?.into(),
            learner_env_steps: progress.env_steps,
        }));
        let progress_at_start = progress.clone();
        let trainer = Self {
            config_yaml,
            run_dir,
            env_id,
            layout,
            row: Window::new(&progress),
            report: Window::new(&progress),
            started: Instant::now(),
            wall_ms_at_start: progress.wall_ms,
            sac,
            replay,
            limiter,
            progress,
            action_scale,
            csv,
            tb,
            prom: Arc::new(LearnerMetrics::default()),
            seconds: Timings::default(),
            last_window: (0.0, 0.0, 0),
            pending: None,
            stop: None,
            policy_tx,
            status: status.clone(),
            lag_warned: None,
            last_checkpoint: (
                Instant::now(),
                (
                    progress_at_start.env_steps,
                    progress_at_start.critic_updates,
                    progress_at_start.stage_epoch,
                ),
            ),
            cfg,
        };
        trainer.update_status();
        tracing::info!(
            "{}; {}; record {} B; K = {} env steps per iteration, G = {} critic updates (target UTD {:.3}, {:?})",
            trainer.replay.online,
            trainer
                .replay
                .offline
                .as_ref()
                .map_or("no offline buffer".to_string(), |b| b.to_string()),
            trainer.layout.record_bytes(),
            trainer.limiter.steps_per_iteration(),
            trainer.cfg.sac.grad_updates_per_step,
            trainer.limiter.target_utd(),
            trainer.cfg.sac.utd_mode,
        );
        Ok((trainer, policy_rx, status))
    }

    pub fn progress(&self) -> &Progress {
        &self.progress
    }
    pub fn layout(&self) -> RecordLayout {
        self.layout
    }
    pub fn env_id(&self) -> &str {
        &self.env_id
    }
    pub fn config_yaml(&self) -> &str {
        &self.config_yaml
    }
    /// Spec 6.4's per-dimension s (`train.data_action_scale`); `None` = no scaling. Actors get it
    /// in `RunInfo.action_scale` and step their envs with a / s.
    pub fn action_scale(&self) -> Option<&[f32]> {
        self.action_scale.as_deref()
    }
    /// The Prometheus state this trainer keeps current (serve it with [`prom::serve`]; the
    /// transports count their own drops into it).
    pub fn metrics(&self) -> Arc<LearnerMetrics> {
        self.prom.clone()
    }

    /// Runs until the budget, a shutdown or the curriculum's end; then writes the final
    /// checkpoint and exports the policy. `initial_stage` is the curriculum server's first
    /// announcement (applied before any record).
    pub fn run(
        mut self,
        mut inputs: TrainerInputs,
        initial_stage: v1::StageEvent,
    ) -> Result<StopReason> {
        let result = self.run_loop(&mut inputs, initial_stage);
        if let Err(e) = &result {
            self.status.failed.store(true, Ordering::Relaxed);
            tracing::error!("training stopped: {}", crate::error::chain(e));
            return result;
        }
        let reason = self.finish(&mut inputs);
        self.status.finished.store(true, Ordering::Relaxed);
        reason
    }

    fn run_loop(
        &mut self,
        inputs: &mut TrainerInputs,
        initial_stage: v1::StageEvent,
    ) -> Result<StopReason> {
        self.on_stage(&initial_stage)?;
        loop {
            while let Ok(event) = inputs.stages.try_recv() {
                self.on_stage(&event)?;
            }
            if *inputs.shutdown.borrow() {
                self.stop.get_or_insert(StopReason::Signal);
            }
            if let Some(reason) = self.stop {
                return Ok(reason);
            }
            self.maybe_report();
            if self.cfg.sac.utd_mode == UtdMode::Sync && self.limiter.due() > 0 {
                self.iterate()?;
                continue;
            }
            if self.progress.env_steps >= self.progress.next_log_at {
                self.progress.next_log_at =
                    next_multiple(self.progress.env_steps, self.cfg.sac.log_freq);
                self.write_row()?;
                continue;
            }
            if self.progress.env_steps >= self.progress.next_checkpoint_at {
                self.progress.next_checkpoint_at =
                    next_multiple(self.progress.env_steps, self.cfg.sac.save_freq);
                self.checkpoint()?;
                continue;
            }
            if self.checkpoint_due_in() == Some(Duration::ZERO) {
                self.checkpoint()?;
                continue;
            }
            if self.progress.env_steps >= self.cfg.train.steps {
                self.stop = Some(StopReason::Budget);
                continue;
            }
            if self.cfg.sac.utd_mode == UtdMode::Async && self.limiter.due() > 0 {
                // Flat out: take what has arrived (at most one queue's worth), then update.
                let mut taken = 0;
                while taken < inputs.data.max_capacity() && !self.at_boundary() {
                    let item = match self.pending.take() {
                        Some(item) => item,
                        None => match inputs.data.try_recv() {
                            Ok(item) => item,
                            Err(_) => break,
                        },
                    };
                    self.ingest(item, inputs)?;
                    taken += 1;
                }
                if !self.at_boundary() {
                    self.iterate()?;
                }
                continue;
            }
            if let Some(item) = self.pending.take() {
                self.ingest(item, inputs)?;
                continue;
            }
            match self.wait(inputs) {
                Wake::Data(item) => self.ingest(item, inputs)?,
                Wake::Stage(event) => self.on_stage(&event)?,
                Wake::Shutdown => {
                    self.stop.get_or_insert(StopReason::Signal);
                }
                Wake::Closed => {
                    self.stop.get_or_insert(StopReason::InputsClosed);
                }
                Wake::Tick => {}
            }
        }
    }

    /// Whether the ingest must pause before the next record (module docs, step 5).
    fn at_boundary(&self) -> bool {
        let p = &self.progress;
        self.limiter.steps_before_due() == 0
            || p.env_steps >= p.next_log_at
            || p.env_steps >= p.next_checkpoint_at
            || p.env_steps >= self.cfg.train.steps
    }

    /// Handles the records of `item` in order until it is used up or a boundary is reached (the
    /// rest waits in `pending`).
    fn ingest(&mut self, mut item: IngestItem, inputs: &mut TrainerInputs) -> Result<()> {
        let start = Instant::now();
        while item.next < item.count {
            if self.at_boundary() || self.stop.is_some() {
                self.pending = Some(item);
                self.add_time(|t| &mut t.ingest, start);
                self.update_status();
                return Ok(());
            }
            let record = item.record(item.next);
            let epoch = record.stage_epoch();
            if epoch < self.progress.stage_epoch {
                // Spec 4 / ARCHITECTURE "Semantics": late records of an ended epoch.
                self.progress.dropped_stale_epoch += 1;
                item.tally
                    .dropped_stale_epoch
                    .fetch_add(1, Ordering::Relaxed);
                item.next += 1;
                continue;
            }
            if epoch > self.progress.stage_epoch {
                // The actor saw the new epoch before we did: wait for its announcement.
                self.add_time(|t| &mut t.ingest, start);
                self.update_status();
                self.await_epoch(epoch, inputs)?;
                return self.ingest(item, inputs);
            }
            let lag = self
                .progress
                .policy_version
                .saturating_sub(record.policy_version());
            self.note_lag(lag, record.actor_id());
            self.replay.online.push_record(&record)?;
            item.tally.accepted.fetch_add(1, Ordering::Relaxed);
            item.next += 1;
            self.progress.env_steps += 1;
            self.limiter.receive(1);
        }
        self.add_time(|t| &mut t.ingest, start);
        self.update_status();
        Ok(())
    }

    /// Blocks until the curriculum server's announcement of `epoch` has been applied (or the run
    /// stops).
    fn await_epoch(&mut self, epoch: u64, inputs: &mut TrainerInputs) -> Result<()> {
        let since = Instant::now();
        let mut warned = false;
        while self.progress.stage_epoch < epoch && self.stop.is_none() {
            let start = Instant::now();
            let TrainerInputs {
                stages,
                shutdown,
                runtime,
                ..
            } = &mut *inputs;
            let wake = runtime.block_on(async {
                tokio::select! {
                    biased;
                    r = shutdown.changed() => match r {
                        Ok(()) if !*shutdown.borrow() => None,
                        _ => Some(Err(StopReason::Signal)),
                    },
                    Some(event) = stages.recv() => Some(Ok(event)),
                    _ = tokio::time::sleep(Duration::from_secs(1)) => None,
                }
            });
            self.add_time(|t| &mut t.wait, start);
            match wake {
                Some(Ok(event)) => self.on_stage(&event)?,
                Some(Err(reason)) => self.stop = Some(reason),
                None if !warned && since.elapsed() > REPORT_EVERY => {
                    warned = true;
                    tracing::warn!(
                        "records of stage epoch {epoch} arrived, but the curriculum server announced only epoch {} so far; holding them",
                        self.progress.stage_epoch
                    );
                }
                None => {}
            }
        }
        Ok(())
    }

    /// Applies a stage announcement (spec 4, ARCHITECTURE "Semantics").
    fn on_stage(&mut self, event: &v1::StageEvent) -> Result<()> {
        if event.stage_epoch < self.progress.stage_epoch {
            tracing::warn!(
                "the curriculum server announced stage epoch {}, older than the learner's {}; ignored",
                event.stage_epoch,
                self.progress.stage_epoch
            );
            return Ok(());
        }
        if event.stage_epoch > self.progress.stage_epoch {
            if event.stage == 2 && self.progress.stage == 1 {
                self.begin_stage_2()?;
            }
            self.progress.stage = event.stage.max(1);
            self.progress.stage_epoch = event.stage_epoch;
            tracing::info!(
                stage = event.stage,
                epoch = event.stage_epoch,
                env_steps = self.progress.env_steps,
                "stage epoch {} begins",
                event.stage_epoch
            );
            self.update_status();
        }
        if event.finished && self.stop.is_none() {
            tracing::info!("the curriculum server finished the run");
            self.stop = Some(StopReason::CurriculumFinished);
        }
        Ok(())
    }

    /// Spec 4.2, 4.4: the stage-1 online buffer becomes the offline buffer (demo transitions
    /// dropped), the online buffer is emptied, and the next `sac.num_seed_steps` env steps are
    /// policy-only; networks, optimiser states and α are kept.
    fn begin_stage_2(&mut self) -> Result<()> {
        let stage_1_len = self.replay.online.len();
        if stage_1_len == 0 {
            tracing::warn!(
                "stage 2 began before any stage-1 transition was stored: keeping the current offline buffer"
            );
        } else {
            self.replay.stage_transition(
                self.cfg.train.load_as_offline_buffer,
                self.cfg.train.load_as_online_buffer,
            )?;
        }
        self.limiter.start_phase(self.cfg.sac.num_seed_steps);
        self.progress.stage_1_steps = Some(self.progress.env_steps);
        tracing::info!(
            env_steps = self.progress.env_steps,
            stage_1_transitions = stage_1_len,
            "stage 2: {}; {}; {} policy-only steps before updates resume",
            self.replay.online,
            self.replay
                .offline
                .as_ref()
                .map_or("no offline buffer".to_string(), |b| b.to_string()),
            self.cfg.sac.num_seed_steps
        );
        Ok(())
    }

    /// One training iteration (spec 5.2) and the policy version it makes.
    fn iterate(&mut self) -> Result<()> {
        let start = Instant::now();
        let g = self.cfg.sac.grad_updates_per_step as usize;
        let b = self.cfg.sac.batch_size as usize;
        let batch = self
            .replay
            .sample(g, b)?
            .to_tensors(self.sac.kind(), self.sac.device());
        let metrics = self.sac.train_iteration(&batch)?;
        for (loss, value) in [
            ("critic loss", metrics.critic_loss),
            ("Q estimate", metrics.q),
            ("actor loss", metrics.actor_loss),
            ("policy entropy", metrics.entropy),
            ("temperature", metrics.temp),
            ("temperature loss", metrics.temp_loss),
        ] {
            if !value.is_finite() {
                return Err(TrainError::NonFiniteLoss {
                    loss,
                    value,
                    first_update: self.progress.critic_updates + 1,
                    last_update: self.progress.critic_updates + metrics.critic_updates,
                    env_steps: self.progress.env_steps,
                });
            }
        }
        self.limiter.iteration_done();
        self.progress.critic_updates += metrics.critic_updates;
        self.progress.actor_updates += metrics.actor_updates;
        self.row.updates.add(&metrics);
        self.report.updates.add(&metrics);
        self.add_time(|t| &mut t.update, start);
        self.progress.policy_version += 1;
        self.publish()?;
        self.update_status();
        Ok(())
    }

    /// Publishes the current actor as `progress.policy_version` (an immutable `Arc`: readers
    /// never see a torn version, and subscribers share one copy).
    fn publish(&mut self) -> Result<()> {
        let start = Instant::now();
        self.check_weights("publish", &[("actor", self.sac.actor_vars())])?;
        let weights = v1::PolicyWeights {
            version: self.progress.policy_version,
            safetensors: policy::encode_actor(&self.sac)?.into(),
            learner_env_steps: self.progress.env_steps,
        };
        self.policy_tx.send_replace(Arc::new(weights));
        self.add_time(|t| &mut t.publish, start);
        Ok(())
    }

    /// Errors with [`TrainError::NonFiniteWeights`] when a variable of `stores` (named
    /// `<prefix>/<name>`) holds a NaN or an infinity.
    fn check_weights(
        &self,
        action: &'static str,
        stores: &[(&str, &tch::nn::VarStore)],
    ) -> Result<()> {
        for (prefix, vs) in stores {
            let mut vars: Vec<(String, tch::Tensor)> = vs.variables().into_iter().collect();
            vars.sort_by(|a, b| a.0.cmp(&b.0));
            for (name, t) in vars {
                if !checkpoint::all_finite(&t)? {
                    return Err(TrainError::NonFiniteWeights {
                        tensor: format!("{prefix}/{name}"),
                        action,
                        critic_updates: self.progress.critic_updates,
                        env_steps: self.progress.env_steps,
                    });
                }
            }
        }
        Ok(())
    }

    /// How long until the wall-time checkpoint (`sac.save_every_s`) is due; `None` while nothing
    /// changed since the last checkpoint.
    fn checkpoint_due_in(&self) -> Option<Duration> {
        let p = &self.progress;
        if self.last_checkpoint.1 == (p.env_steps, p.critic_updates, p.stage_epoch) {
            return None;
        }
        let every = Duration::from_secs_f64(self.cfg.sac.save_every_s);
        Some(every.saturating_sub(self.last_checkpoint.0.elapsed()))
    }

    fn checkpoint(&mut self) -> Result<()> {
        let start = Instant::now();
        self.check_weights(
            "checkpoint",
            &[
                ("actor", self.sac.actor_vars()),
                ("critic", self.sac.critic_vars()),
                ("target", self.sac.target_critic_vars()),
                ("temperature", self.sac.temperature_vars()),
            ],
        )?;
        self.progress.wall_ms = self.wall_ms();
        let dir = checkpoint::checkpoint_dir(&self.run_dir);
        let extras = Extras {
            run_name: &self.cfg.name,
            config_yaml: &self.config_yaml,
            progress: &self.progress,
            limiter: &self.limiter,
        };
        let saved = checkpoint::save(&dir, &self.sac, &mut self.replay, &extras)?;
        let p = &self.progress;
        self.last_checkpoint = (
            Instant::now(),
            (p.env_steps, p.critic_updates, p.stage_epoch),
        );
        self.add_time(|t| &mut t.checkpoint, start);
        tracing::info!(
            env_steps = self.progress.env_steps,
            generation = saved.manifest.generation,
            replay_mb = saved.manifest.replay_bytes as f64 / 1e6,
            replay_segments_written = saved.replay_files_written,
            replay_mb_written = saved.replay_bytes_written as f64 / 1e6,
            "checkpoint written to {} in {:.2} s",
            dir.display(),
            start.elapsed().as_secs_f64()
        );
        Ok(())
    }

    /// `policy.safetensors` + `policy.json` in the run directory (see docs/POLICY.md).
    fn export_policy(&self) -> Result<()> {
        self.check_weights("export", &[("actor", self.sac.actor_vars())])?;
        let bytes = policy::encode_actor(&self.sac)?;
        let shape = PolicyShape::from_config(&self.cfg, self.sac.obs_dim(), self.sac.action_dim());
        let desc = PolicyDescription {
            format: policy::FORMAT.into(),
            env_id: self.env_id.clone(),
            tensors: policy::tensor_names(shape.actor_features.len()),
            shape,
            activation: "relu".into(),
            action_scale: self.action_scale.clone(),
            policy_version: self.progress.policy_version,
            env_steps: self.progress.env_steps,
        };
        for (name, data) in [
            ("policy.safetensors", bytes),
            ("policy.json", desc.to_json().into_bytes()),
        ] {
            let path = self.run_dir.join(name);
            rfcl_core::atomic::atomic_write(&path, &data).map_err(|source| TrainError::Io {
                what: "writing",
                path,
                source,
            })?;
        }
        Ok(())
    }

    /// The end of the run: count what is left unused, last metrics row, final checkpoint, the
    /// exported policy.
    fn finish(&mut self, inputs: &mut TrainerInputs) -> Result<StopReason> {
        let reason = self.stop.unwrap_or(StopReason::InputsClosed);
        let mut left = self.pending.take().map_or(0, |i| i.remaining() as u64);
        while let Ok(item) = inputs.data.try_recv() {
            left += item.remaining() as u64;
        }
        self.progress.discarded += left;
        if self.row.env_steps < self.progress.env_steps || self.row.updates.iterations() > 0 {
            self.write_row()?;
        }
        self.checkpoint()?;
        self.export_policy()?;
        self.update_status();
        tracing::info!(
            ?reason,
            env_steps = self.progress.env_steps,
            critic_updates = self.progress.critic_updates,
            policy_version = self.progress.policy_version,
            dropped_stale_epoch = self.progress.dropped_stale_epoch,
            unused_records = left,
            "training finished; policy exported to {}",
            self.run_dir.join("policy.safetensors").display()
        );
        Ok(reason)
    }

    fn wait(&mut self, inputs: &mut TrainerInputs) -> Wake {
        let start = Instant::now();
        let mut timeout = REPORT_EVERY.saturating_sub(self.report.start.elapsed());
        if let Some(due) = self.checkpoint_due_in() {
            timeout = timeout.min(due);
        }
        let TrainerInputs {
            data,
            stages,
            shutdown,
            runtime,
        } = inputs;
        let wake = runtime.block_on(async {
            tokio::select! {
                biased;
                r = shutdown.changed() => match r {
                    Ok(()) if !*shutdown.borrow() => Wake::Tick,
                    _ => Wake::Shutdown,
                },
                Some(event) = stages.recv() => Wake::Stage(event),
                item = data.recv() => item.map_or(Wake::Closed, Wake::Data),
                _ = tokio::time::sleep(timeout.max(Duration::from_millis(10))) => Wake::Tick,
            }
        });
        self.add_time(|t| &mut t.wait, start);
        wake
    }

    fn write_row(&mut self) -> Result<()> {
        let window = std::mem::replace(&mut self.row, Window::new(&self.progress));
        let secs = window.start.elapsed().as_secs_f64().max(1e-9);
        let row = Row {
            env_steps: self.progress.env_steps,
            stage: self.progress.stage,
            stage_epoch: self.progress.stage_epoch,
            policy_version: self.progress.policy_version,
            critic_updates_total: self.progress.critic_updates,
            stage_1_steps: self.progress.stage_1_steps,
            sps: (self.progress.env_steps - window.env_steps) as f64 / secs,
            total_s: self.wall_ms() as f64 / 1000.0,
            iterations_total: self.limiter.iterations(),
            utd: self.limiter.achieved_utd(),
            utd_target: self.limiter.target_utd(),
            updates_per_s: (self.progress.critic_updates - window.critic_updates) as f64 / secs,
            replay_online: self.replay.online.len(),
            replay_offline: self.replay.offline.as_ref().map_or(0, ReplayBuffer::len),
            replay_bytes: self.replay.bytes(),
            dropped_stale_epoch: self.progress.dropped_stale_epoch,
            policy_lag_max: window.lag_max,
            timings: window.timings,
            updates: window.updates,
        };
        self.csv.write(&row).map_err(|source| TrainError::Io {
            what: "writing",
            path: self.csv.path().to_path_buf(),
            source,
        })?;
        self.tb
            .scalars(row.env_steps, row.scalars())
            .map_err(|source| TrainError::Io {
                what: "writing",
                path: self.tb.path().to_path_buf(),
                source,
            })
    }

    /// The periodic progress line on stderr.
    fn maybe_report(&mut self) {
        if self.report.start.elapsed() < REPORT_EVERY {
            return;
        }
        let w = std::mem::replace(&mut self.report, Window::new(&self.progress));
        let secs = w.start.elapsed().as_secs_f64();
        let t = w.timings;
        self.last_window = (
            (self.progress.critic_updates - w.critic_updates) as f64 / secs,
            (self.progress.env_steps - w.env_steps) as f64 / secs,
            w.lag_max,
        );
        self.update_status();
        tracing::info!(
            "stage {} | env steps {} ({:.1}/s) | critic updates {} ({:.1}/s) | UTD {:.3} (target {:.3}) | online {}/{} offline {} ({:.1} MB) | dropped stale {} | policy v{} lag<={} | time: wait {:.0}% ingest {:.0}% update {:.0}% publish {:.0}% checkpoint {:.0}%",
            self.progress.stage,
            self.progress.env_steps,
            (self.progress.env_steps - w.env_steps) as f64 / secs,
            self.progress.critic_updates,
            (self.progress.critic_updates - w.critic_updates) as f64 / secs,
            self.limiter.achieved_utd(),
            self.limiter.target_utd(),
            self.replay.online.len(),
            self.replay.online.capacity(),
            self.replay.offline.as_ref().map_or(0, ReplayBuffer::len),
            self.replay.bytes() as f64 / 1e6,
            self.progress.dropped_stale_epoch,
            self.progress.policy_version,
            w.lag_max,
            100.0 * t.wait / secs,
            100.0 * t.ingest / secs,
            100.0 * t.update / secs,
            100.0 * t.publish / secs,
            100.0 * t.checkpoint / secs,
        );
    }

    fn note_lag(&mut self, lag: u64, actor_id: u32) {
        self.row.lag_max = self.row.lag_max.max(lag);
        self.report.lag_max = self.report.lag_max.max(lag);
        if lag > self.cfg.service.max_policy_lag
            && self.lag_warned.is_none_or(|t| t.elapsed() >= REPORT_EVERY)
        {
            self.lag_warned = Some(Instant::now());
            tracing::warn!(
                actor = actor_id,
                lag,
                "actor {actor_id} acts with a policy {lag} versions old (service.max_policy_lag = {})",
                self.cfg.service.max_policy_lag
            );
        }
    }

    fn add_time(&mut self, field: impl Fn(&mut Timings) -> &mut f64, since: Instant) {
        let secs = since.elapsed().as_secs_f64();
        *field(&mut self.row.timings) += secs;
        *field(&mut self.report.timings) += secs;
        *field(&mut self.seconds) += secs;
    }

    fn wall_ms(&self) -> u64 {
        self.wall_ms_at_start + self.started.elapsed().as_millis() as u64
    }

    fn update_status(&self) {
        let p = &self.progress;
        self.status.set(StatusSnapshot {
            env_steps: p.env_steps,
            critic_updates: p.critic_updates,
            policy_version: p.policy_version,
            stage_epoch: p.stage_epoch,
            dropped_stale_epoch: p.dropped_stale_epoch,
        });
        let buffer = |b: &ReplayBuffer| prom::BufferStats {
            len: b.len(),
            capacity: b.capacity(),
            bytes: b.bytes(),
        };
        let (updates_per_s, env_steps_per_s, lag) = self.last_window;
        self.prom.set(prom::Snapshot {
            env_steps: p.env_steps,
            critic_updates: p.critic_updates,
            actor_updates: p.actor_updates,
            iterations: self.limiter.iterations(),
            updates_per_s,
            env_steps_per_s,
            utd: self.limiter.achieved_utd(),
            utd_target: self.limiter.target_utd(),
            online: buffer(&self.replay.online),
            offline: self.replay.offline.as_ref().map(buffer),
            stage: p.stage,
            stage_epoch: p.stage_epoch,
            policy_version: p.policy_version,
            policy_lag_max: lag.max(self.report.lag_max),
            dropped_stale_epoch: p.dropped_stale_epoch,
            unused_at_end: p.discarded,
            seconds: self.seconds,
        });
    }
}

enum Wake {
    Data(IngestItem),
    Stage(v1::StageEvent),
    Shutdown,
    Closed,
    Tick,
}

/// The smallest multiple of `every` above `at` (never, for `every` 0).
fn next_multiple(at: u64, every: u64) -> u64 {
    at.checked_div(every).map_or(u64::MAX, |q| (q + 1) * every)
}

/// Spec 6.4's per-dimension s, when `train.data_action_scale` is set.
fn action_scale(cfg: &RunConfig, demos: &DemoSet) -> Result<Option<Vec<f32>>> {
    Ok(cfg
        .train
        .data_action_scale
        .map(|scale| data_action_scale(&demos.demos, demos.action_dim, scale))
        .transpose()?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn boundaries_are_the_next_multiples() {
        assert_eq!(next_multiple(0, 100), 100);
        assert_eq!(next_multiple(100, 100), 200);
        assert_eq!(next_multiple(150, 100), 200);
        assert_eq!(next_multiple(5, 0), u64::MAX);
    }
}
