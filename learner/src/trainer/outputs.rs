//! What leaves the trainer: policy versions (published to the transports), checkpoints and the
//! exported policy, each after checking that the weights are finite.
use std::sync::Arc;
use std::time::{Duration, Instant};

use prost::bytes::Bytes;
use rfcl_policy::{self as policy, PolicyDescription, PolicyShape};
use tokio::sync::watch;

use super::{Result, TrainError, Trainer};
use crate::checkpoint::{self, Extras};

/// One published policy version, as the trainer hands it to the transports (gRPC's WatchPolicy,
/// the shared-memory publisher), which convert it to their own wire form.
#[derive(Debug, Clone, PartialEq)]
pub struct PublishedPolicy {
    pub version: u64,
    /// The actor network in the policy format (`rfcl_policy::encode_vars`). `Bytes`: every
    /// subscriber shares the one buffer.
    pub safetensors: Bytes,
    /// The learner's env-step count when this version was published.
    pub learner_env_steps: u64,
}

/// The newest published policy: what the transports watch.
pub type PolicyWatch = watch::Receiver<Arc<PublishedPolicy>>;

impl Trainer {
    /// Publishes the current actor as `progress.policy_version` (an immutable `Arc`: readers
    /// never see a torn version, and subscribers share one copy).
    pub(super) fn publish(&mut self) -> Result<()> {
        let start = Instant::now();
        self.check_weights("publish", &[("actor", self.sac.actor_vars())])?;
        let weights = PublishedPolicy {
            version: self.progress.policy_version,
            safetensors: policy::encode_vars(self.sac.actor_vars())?.into(),
            learner_env_steps: self.progress.env_steps,
        };
        self.policy_tx.send_replace(Arc::new(weights));
        self.add_time(|t| &mut t.publish, start);
        Ok(())
    }

    /// Errors with [`TrainError::NonFiniteWeights`] when a variable of `stores` (named
    /// `<prefix>/<name>`) holds a NaN or an infinity.
    pub(super) fn check_weights(
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
    pub(super) fn checkpoint_due_in(&self) -> Option<Duration> {
        let p = &self.progress;
        if self.last_checkpoint.1 == (p.env_steps, p.critic_updates, p.stage_epoch) {
            return None;
        }
        let every = Duration::from_secs_f64(self.cfg.sac.save_every_s);
        Some(every.saturating_sub(self.last_checkpoint.0.elapsed()))
    }

    pub(super) fn checkpoint(&mut self) -> Result<()> {
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
    pub(super) fn export_policy(&self) -> Result<()> {
        self.check_weights("export", &[("actor", self.sac.actor_vars())])?;
        let bytes = policy::encode_vars(self.sac.actor_vars())?;
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
}
