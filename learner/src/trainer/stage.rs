//! The curriculum's stage changes as the trainer applies them (spec 4): a new stage epoch, and at
//! the move from the reverse to the forward curriculum the buffers' stage transition.
use super::setup::stage_2_init_seed;
use super::{Result, StopReason, Trainer};
use crate::stages::{Stage, StageAnnouncement};

impl Trainer {
    /// Applies a stage announcement (spec 4; docs/LEARNER.md "Stage transition").
    pub(super) fn on_stage(&mut self, event: &StageAnnouncement) -> Result<()> {
        if event.epoch < self.progress.stage_epoch {
            tracing::warn!(
                "the curriculum server announced stage epoch {}, older than the learner's {}; ignored",
                event.epoch,
                self.progress.stage_epoch
            );
            return Ok(());
        }
        if event.epoch > self.progress.stage_epoch {
            let current = Stage::from_number(self.progress.stage);
            if current == Stage::Reverse && event.stage == Stage::Forward {
                self.begin_stage_2()?;
            }
            self.progress.stage = event.stage.number();
            self.progress.stage_epoch = event.epoch;
            tracing::info!(
                stage = event.stage.number(),
                epoch = event.epoch,
                env_steps = self.progress.env_steps,
                "stage epoch {} begins",
                event.epoch
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
    /// policy-only; networks, optimiser states and α are kept (spec 4.1), unless
    /// `train.load_actor` / `train.load_critic` say to start the actor / the critics afresh.
    pub(super) fn begin_stage_2(&mut self) -> Result<()> {
        let (keep_actor, keep_critic) = (self.cfg.train.load_actor, self.cfg.train.load_critic);
        if !keep_actor || !keep_critic {
            self.sac.reinitialise(
                !keep_actor,
                !keep_critic,
                &self.cfg.network,
                stage_2_init_seed(self.cfg.seed),
            )?;
            tracing::info!(
                actor = !keep_actor,
                critic = !keep_critic,
                "stage 2 starts these networks afresh (train.load_actor / train.load_critic false)"
            );
            if !keep_actor {
                // Stage 2's first episodes act with the fresh actor, not the stage-1 one.
                self.progress.policy_version += 1;
                self.publish()?;
            }
        }
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
}
