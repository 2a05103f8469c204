//! Building the trainer: a fresh run or one resumed from its checkpoint.
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use rfcl_core::config::RunConfig;
use rfcl_core::demo::DemoSet;
use rfcl_core::transition::RecordLayout;
use tokio::sync::watch;

use super::{
    LearnerStatus, PolicyWatch, PublishedPolicy, Result, TrainError, Trainer, Window, WindowStats,
};
use crate::checkpoint::{self, Manifest, Progress};
use crate::limiter::UtdLimiter;
use crate::metrics::{MetricsCsv, Timings};
use crate::prom::LearnerMetrics;
use crate::replay::{data_action_scale, offline_from_demos, Replay, ReplayBuffer};
use crate::sac::Sac;
use crate::stages::StageAnnouncement;
use crate::tensorboard::EventWriter;

/// Seeds derived from the run seed: the agent takes the run seed itself (network init, policy
/// noise, target members), the replay sampler this one.
pub fn replay_seed(run_seed: u64) -> u64 {
    run_seed ^ 0x9E37_79B9_7F4A_7C15
}

/// The seed of the networks that stage 2 starts afresh (`train.load_actor` / `load_critic`
/// false): not the run seed, whose initialisation the stage-1 networks started from.
pub fn stage_2_init_seed(run_seed: u64) -> u64 {
    run_seed ^ 0xD1B5_4A32_D192_ED03
}

/// K = `env.num_envs · sac.steps_per_env`, env steps per training iteration (spec 5.2).
pub fn steps_per_iteration(cfg: &RunConfig) -> u64 {
    u64::from(cfg.env.num_envs) * u64::from(cfg.sac.steps_per_env)
}

/// What a trainer starts from, fresh or restored from a checkpoint.
struct Start {
    sac: Sac,
    replay: Replay,
    limiter: UtdLimiter,
    progress: Progress,
}

impl Trainer {
    /// A new run: a fresh agent, the demos as the offline buffer (spec 6.2, with
    /// `data_action_scale`, 6.4; none with `train_on_demo_actions: false`, 6.3), an empty online
    /// buffer, and the stage the curriculum server announced first.
    pub fn fresh(
        cfg: RunConfig,
        demos: &DemoSet,
        run_dir: PathBuf,
        first_stage: &StageAnnouncement,
    ) -> Result<(Self, PolicyWatch, Arc<LearnerStatus>)> {
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
        let start = Start {
            sac,
            replay,
            limiter,
            progress: Progress {
                policy_version: 1,
                stage: first_stage.stage.number(),
                stage_epoch: first_stage.epoch,
                next_checkpoint_at: cfg.sac.save_freq,
                next_log_at: cfg.sac.log_freq,
                ..Progress::default()
            },
        };
        Self::assemble(cfg, demos, run_dir, start, action_scale, false)
    }

    /// Continues the run whose checkpoint `manifest` describes: weights, optimiser states,
    /// temperature, RNGs, counters, UTD limiter and both buffers as they were. A backlog of owed
    /// iterations (a changed schedule or mode) is clamped, not burst.
    pub fn resume(
        cfg: RunConfig,
        demos: &DemoSet,
        run_dir: PathBuf,
        manifest: &Manifest,
    ) -> Result<(Self, PolicyWatch, Arc<LearnerStatus>)> {
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
        let start = Start {
            progress: manifest.progress.clone(),
            sac,
            replay,
            limiter,
        };
        Self::assemble(cfg, demos, run_dir, start, action_scale, true)
    }

    /// The trainer of `start`; `resumed`: its metrics files go on from `start`'s env steps.
    fn assemble(
        cfg: RunConfig,
        demos: &DemoSet,
        run_dir: PathBuf,
        start: Start,
        action_scale: Option<Vec<f32>>,
        resumed: bool,
    ) -> Result<(Self, PolicyWatch, Arc<LearnerStatus>)> {
        let Start {
            sac,
            replay,
            limiter,
            progress,
        } = start;
        let resumed_at = resumed.then_some(progress.env_steps);
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
        let (policy_tx, policy_rx) = watch::channel(Arc::new(PublishedPolicy {
            version: progress.policy_version,
            safetensors: rfcl_policy::encode_vars(sac.actor_vars())?.into(),
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
            last_window: WindowStats::default(),
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
}

/// Spec 6.4's per-dimension s, when `train.data_action_scale` is set.
fn action_scale(cfg: &RunConfig, demos: &DemoSet) -> Result<Option<Vec<f32>>> {
    Ok(cfg
        .train
        .data_action_scale
        .map(|scale| data_action_scale(&demos.demos, demos.action_dim, scale))
        .transpose()?)
}
