//! What the trainer reports: `metrics.csv` and TensorBoard rows, the periodic progress line, the
//! policy-lag warning, time per activity, and the status the service and Prometheus read.
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use super::{Result, TrainError, Trainer, REPORT_EVERY};
use crate::checkpoint::Progress;
use crate::metrics::{Row, Timings, UpdateMeans};
use crate::prom;
use crate::replay::ReplayBuffer;

/// What the service reads of the training thread's state (Health, RunInfo).
#[derive(Debug, Default)]
pub struct LearnerStatus {
    /// Written by the training thread at consistent points (after an iteration, when the ingest
    /// pauses), so a reader never sees env steps and updates of different moments.
    snapshot: std::sync::Mutex<StatusSnapshot>,
    /// The last progress window (the periodic log line's figures); `None` before the first.
    window: std::sync::Mutex<Option<WindowStats>>,
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

    /// The last progress window, for the Health RPC (the dashboard's learner panel).
    pub fn window(&self) -> Option<WindowStats> {
        *self.window.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn set_window(&self, window: WindowStats) {
        *self.window.lock().unwrap_or_else(|p| p.into_inner()) = Some(window);
    }
}

/// What the learner did over one progress window: rates, the mean update metrics, and seconds
/// per activity.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct WindowStats {
    pub seconds: f64,
    pub updates_per_s: f64,
    pub env_steps_per_s: f64,
    pub utd: f64,
    pub utd_target: f64,
    pub policy_lag_max: u64,
    /// Means of the spec 5.8 update tags over the window (`UpdateMetrics::tagged` order:
    /// critic loss, Q, actor loss, entropy, temperature, temperature loss); `None` when no
    /// update ran.
    pub update_means: [Option<f64>; 6],
    pub timings: Timings,
}

/// Activity of one window (a metrics row or a progress line).
#[derive(Debug, Clone)]
pub(super) struct Window {
    pub(super) start: Instant,
    pub(super) env_steps: u64,
    pub(super) critic_updates: u64,
    pub(super) updates: UpdateMeans,
    pub(super) timings: Timings,
    pub(super) lag_max: u64,
}

impl Window {
    pub(super) fn new(progress: &Progress) -> Self {
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

impl Trainer {
    pub(super) fn write_row(&mut self) -> Result<()> {
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
    pub(super) fn maybe_report(&mut self) {
        if self.report.start.elapsed() < REPORT_EVERY {
            return;
        }
        let w = std::mem::replace(&mut self.report, Window::new(&self.progress));
        let secs = w.start.elapsed().as_secs_f64();
        let t = w.timings;
        self.last_window = WindowStats {
            seconds: secs,
            updates_per_s: (self.progress.critic_updates - w.critic_updates) as f64 / secs,
            env_steps_per_s: (self.progress.env_steps - w.env_steps) as f64 / secs,
            utd: self.limiter.achieved_utd(),
            utd_target: self.limiter.target_utd(),
            policy_lag_max: w.lag_max,
            update_means: w.updates.means(),
            timings: t,
        };
        self.status.set_window(self.last_window);
        self.update_status();
        tracing::info!(
            "stage {} | env steps {} ({:.1}/s) | critic updates {} ({:.1}/s) | UTD {:.3} (target {:.3}) | online {}/{} offline {} ({:.1} MB) | dropped stale {} | policy v{} lag<={} | time: wait {:.0}% ingest {:.0}% update {:.0}% publish {:.0}% checkpoint {:.0}%",
            self.progress.stage,
            self.progress.env_steps,
            self.last_window.env_steps_per_s,
            self.progress.critic_updates,
            self.last_window.updates_per_s,
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

    pub(super) fn note_lag(&mut self, lag: u64, actor_id: u32) {
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

    pub(super) fn add_time(&mut self, field: impl Fn(&mut Timings) -> &mut f64, since: Instant) {
        let secs = since.elapsed().as_secs_f64();
        *field(&mut self.row.timings) += secs;
        *field(&mut self.report.timings) += secs;
        *field(&mut self.seconds) += secs;
    }

    pub(super) fn wall_ms(&self) -> u64 {
        self.wall_ms_at_start + self.started.elapsed().as_millis() as u64
    }

    pub(super) fn update_status(&self) {
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
        let WindowStats {
            updates_per_s,
            env_steps_per_s,
            policy_lag_max: lag,
            ..
        } = self.last_window;
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
