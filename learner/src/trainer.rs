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
//! 4. the budget (`train.steps`), with one last iteration when the budget falls between two, so
//!    that the final policy is trained on every env step;
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
//!
//! The trainer's concerns, one module each: `setup` builds it (fresh or resumed), this module
//! runs the loop, `stage` applies the curriculum's stage changes, `outputs` publishes,
//! checkpoints and exports, and `telemetry` keeps the metrics, the progress line and the status
//! the service reads ([`LearnerStatus`]). The curriculum server's v1 stage events are converted once, in
//! [`crate::stages`], into [`StageAnnouncement`]s.
mod outputs;
mod setup;
mod stage;
mod telemetry;

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use rfcl_core::config::{RunConfig, UtdMode};
use rfcl_core::transition::RecordLayout;
use rfcl_policy::PolicyError;
use thiserror::Error;
use tokio::sync::{mpsc, watch};

use crate::checkpoint::{CheckpointError, Progress};
use crate::error::LearnerError;
use crate::ingest::IngestItem;
use crate::limiter::UtdLimiter;
use crate::metrics::{MetricsCsv, Timings};
use crate::prom::LearnerMetrics;
use crate::replay::Replay;
use crate::sac::Sac;
use crate::stages::StageAnnouncement;
use crate::tensorboard::EventWriter;

pub use outputs::{PolicyWatch, PublishedPolicy};
pub use setup::{replay_seed, steps_per_iteration};
use telemetry::Window;
pub use telemetry::{LearnerStatus, StatusSnapshot, WindowStats};

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
    pub stages: mpsc::UnboundedReceiver<StageAnnouncement>,
    pub shutdown: watch::Receiver<bool>,
    /// The runtime whose timers and channels the thread waits on.
    pub runtime: tokio::runtime::Handle,
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
    /// The last progress window (rates, policy lag, update means, time per activity).
    last_window: WindowStats,
    /// A batch partly handled (the ingest paused at a boundary).
    pending: Option<IngestItem>,
    stop: Option<StopReason>,
    row: Window,
    report: Window,
    started: Instant,
    wall_ms_at_start: u64,
    policy_tx: watch::Sender<Arc<PublishedPolicy>>,
    status: Arc<LearnerStatus>,
    /// Last time a policy-lag warning was logged.
    lag_warned: Option<Instant>,
    /// When the last checkpoint was written (or this process started) and the env steps, critic
    /// updates and stage epoch it held (the wall-time cadence skips a learner with nothing new).
    last_checkpoint: (Instant, (u64, u64, u64)),
}

impl Trainer {
    /// Spreads the critic ensemble's members over `threads` threads (see
    /// [`Sac::set_member_threads`]); the maths stay the same.
    pub fn set_member_threads(&mut self, threads: usize) {
        self.sac.set_member_threads(threads);
    }

    /// How critic updates take their gradients on the CPU (`learner.backend`, see
    /// [`Sac::set_backend`]); the maths stay the same.
    pub fn set_backend(&mut self, backend: rfcl_core::config::Backend) {
        self.sac.set_backend(backend);
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

    /// The Prometheus state this trainer keeps current (serve it with [`crate::prom::serve`]; the
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
        initial_stage: StageAnnouncement,
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
        initial_stage: StageAnnouncement,
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
                // The final policy learns from every env step of the budget, so that it is the
                // one evaluated at the budget's eval point (docs/LEARNER.md, "Training schedule").
                if self.limiter.updating()
                    && self.policy_tx.borrow().learner_env_steps < self.progress.env_steps
                {
                    self.iterate()?;
                }
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
                // Spec 4: late records of an ended epoch.
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
}

enum Wake {
    Data(IngestItem),
    Stage(StageAnnouncement),
    Shutdown,
    Closed,
    Tick,
}

/// The smallest multiple of `every` above `at` (never, for `every` 0).
fn next_multiple(at: u64, every: u64) -> u64 {
    at.checked_div(every).map_or(u64::MAX, |q| (q + 1) * every)
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
