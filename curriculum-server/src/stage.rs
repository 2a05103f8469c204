//! The stage machine (spec 2.7, 4): stage 1 (reverse curriculum) until the reverse curriculum is
//! done, then stage 2 (forward curriculum), or the end of the run with `stage_1_only`. Every change
//! bumps the stage epoch.
use rfcl_core::config::StagePlan;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Stage {
    /// Stage 1: resets to demo states (spec 2).
    Reverse,
    /// Stage 2: resets to levels (spec 3).
    Forward,
    /// The run is over (stage 1 ended under `stage_1_only`, or the evaluations reached
    /// `service.stop_at_eval_success`): nothing more to hand out.
    Finished,
}

/// A stage change, as announced to the learner and the actors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct StageChange {
    pub from: Stage,
    pub to: Stage,
    /// The new stage epoch.
    pub epoch: u64,
    /// Env steps (over the whole run) when the change happened.
    pub env_steps: u64,
}

/// Where the run stands: what the learner and the actors are told at every stage change.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct StageStatus {
    /// The stage now; `Finished` once the run is over.
    pub stage: Stage,
    /// The curriculum stage the run is in or, once finished, the one it finished in (never
    /// `Finished`): a finished run still says which curriculum its last episodes came from.
    pub curriculum_stage: Stage,
    /// Increases by one on every stage change; starts at 0.
    pub epoch: u64,
    /// Env steps at which stage 1 ended, once it has.
    pub stage_1_end_env_steps: Option<u64>,
}

impl StageStatus {
    pub fn finished(&self) -> bool {
        self.stage == Stage::Finished
    }

    /// The stage number on the wire and the dashboard: 1 (reverse) or 2 (forward); a finished run
    /// keeps the number of the stage it finished in.
    pub fn number(&self) -> u32 {
        match self.curriculum_stage {
            Stage::Forward => 2,
            Stage::Reverse | Stage::Finished => 1,
        }
    }
}

/// Why a restored run cannot follow the plan of the config it resumes under.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ReplanError {
    #[error(
        "the run is still in stage 1 (the reverse curriculum), so it cannot be resumed \
         forward-only (train.stage_2_only: true, or train.mode: rlpd); start a new run for that"
    )]
    ForwardOnlyInStage1,
    #[error(
        "the run is past stage 1 (its reverse curriculum ended), so it cannot be resumed with \
         train.stage_1_only: true"
    )]
    Stage1OnlyInStage2,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct StageMachine {
    stage: Stage,
    epoch: u64,
    stage_1_only: bool,
    stage_1_end_env_steps: Option<u64>,
    /// The stage the run finished in (absent from older snapshots: stage 1).
    #[serde(default)]
    finished_in: Option<Stage>,
}

impl StageMachine {
    /// Starts in stage 1, or directly in stage 2 for a forward-only run (stage 1 then ended at
    /// step 0). The plan comes from [`TrainConfig::stage_plan`](rfcl_core::config::TrainConfig::stage_plan), which refuses contradictory options.
    pub fn new(plan: StagePlan) -> Self {
        let (stage, stage_1_end_env_steps) = match plan {
            StagePlan::ForwardOnly => (Stage::Forward, Some(0)),
            StagePlan::Both | StagePlan::ReverseOnly => (Stage::Reverse, None),
        };
        Self {
            stage,
            epoch: 0,
            stage_1_only: plan == StagePlan::ReverseOnly,
            stage_1_end_env_steps,
            finished_in: None,
        }
    }

    pub fn stage(&self) -> Stage {
        self.stage
    }

    /// Whether stage 2 has begun: the forward curriculum has handed out levels (or could have).
    pub fn forward_started(&self) -> bool {
        self.stage == Stage::Forward || self.finished_in == Some(Stage::Forward)
    }

    /// Where the run stands, all of it at once.
    pub fn status(&self) -> StageStatus {
        StageStatus {
            stage: self.stage,
            curriculum_stage: self.finished_in.unwrap_or(self.stage),
            epoch: self.epoch,
            stage_1_end_env_steps: self.stage_1_end_env_steps,
        }
    }

    /// [`StageStatus::number`] of the current status.
    pub fn number(&self) -> u32 {
        self.status().number()
    }

    /// Ends the run at `env_steps`, in whichever stage it is (the stop rule). Does nothing when it
    /// is already over.
    pub fn finish(&mut self, env_steps: u64) -> Option<StageChange> {
        if self.stage == Stage::Finished {
            return None;
        }
        let from = self.stage;
        self.finished_in = Some(from);
        self.stage = Stage::Finished;
        self.epoch += 1;
        Some(StageChange {
            from,
            to: Stage::Finished,
            epoch: self.epoch,
            env_steps,
        })
    }

    /// Increases by one on every stage change; starts at 0.
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// Env steps at which stage 1 ended (`train_stats/stage_1_steps`), once it has.
    pub fn stage_1_end_env_steps(&self) -> Option<u64> {
        self.stage_1_end_env_steps
    }

    /// Brings a machine restored from a snapshot in line with the plan of the config the run
    /// resumes under, at `env_steps`. A run that stopped at the end of stage 1 under
    /// `stage_1_only` goes on into stage 2 when resumed without it, the researcher's natural
    /// "look at stage 1, then continue"; a run still in stage 1 resumed with `stage_1_only` stops
    /// at its end. A run past stage 1 cannot be resumed with `stage_1_only`, nor one still in
    /// stage 1 forward-only: either would give the stage-1 end a meaning it does not have. A run
    /// the stop rule finished stays finished.
    pub fn replan(
        &mut self,
        plan: StagePlan,
        env_steps: u64,
    ) -> Result<Option<StageChange>, ReplanError> {
        // Snapshots from before `finished_in` could only finish at the end of stage 1.
        let finished_in = self.finished_in.unwrap_or(Stage::Reverse);
        let in_stage_1 = self.stage == Stage::Reverse;
        let past_stage_1 = self.forward_started();
        match plan {
            StagePlan::ForwardOnly if in_stage_1 => Err(ReplanError::ForwardOnlyInStage1),
            StagePlan::ReverseOnly if past_stage_1 => Err(ReplanError::Stage1OnlyInStage2),
            StagePlan::ReverseOnly => {
                self.stage_1_only = true;
                Ok(None)
            }
            StagePlan::Both | StagePlan::ForwardOnly => {
                self.stage_1_only = false;
                let stopped_after_stage_1 = self.stage == Stage::Finished
                    && finished_in == Stage::Reverse
                    && self.stage_1_end_env_steps.is_some();
                if !stopped_after_stage_1 {
                    return Ok(None);
                }
                self.stage = Stage::Forward;
                self.finished_in = None;
                self.epoch += 1;
                Ok(Some(StageChange {
                    from: Stage::Finished,
                    to: Stage::Forward,
                    epoch: self.epoch,
                    env_steps,
                }))
            }
        }
    }

    /// Ends stage 1 at `env_steps` (spec 2.7, 4): to stage 2, or to the end with `stage_1_only`.
    /// Does nothing outside stage 1.
    pub fn end_stage_1(&mut self, env_steps: u64) -> Option<StageChange> {
        if self.stage != Stage::Reverse {
            return None;
        }
        let to = if self.stage_1_only {
            Stage::Finished
        } else {
            Stage::Forward
        };
        self.stage = to;
        self.epoch += 1;
        self.stage_1_end_env_steps = Some(env_steps);
        if to == Stage::Finished {
            self.finished_in = Some(Stage::Reverse);
        }
        Some(StageChange {
            from: Stage::Reverse,
            to,
            epoch: self.epoch,
            env_steps,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rfcl_core::config::TrainConfig;

    #[test]
    fn stage_1_then_stage_2_once() {
        let mut stages = StageMachine::new(StagePlan::Both);
        assert_eq!((stages.stage(), stages.epoch()), (Stage::Reverse, 0));
        assert_eq!(stages.stage_1_end_env_steps(), None);
        assert_eq!(
            stages.end_stage_1(1234),
            Some(StageChange {
                from: Stage::Reverse,
                to: Stage::Forward,
                epoch: 1,
                env_steps: 1234
            })
        );
        assert_eq!(stages.end_stage_1(2000), None);
        assert_eq!((stages.stage(), stages.epoch()), (Stage::Forward, 1));
        assert_eq!(stages.stage_1_end_env_steps(), Some(1234));
    }

    #[test]
    fn the_stop_rule_finishes_the_run_in_either_stage() {
        let mut stages = StageMachine::new(StagePlan::Both);
        let change = stages.finish(900).unwrap();
        assert_eq!(
            (change.from, change.to, change.epoch),
            (Stage::Reverse, Stage::Finished, 1)
        );
        assert_eq!((stages.number(), stages.stage_1_end_env_steps()), (1, None));
        assert_eq!(stages.finish(950), None);

        let mut stages = StageMachine::new(StagePlan::Both);
        stages.end_stage_1(500);
        assert_eq!(stages.number(), 2);
        assert_eq!(
            stages.finish(900).map(|c| (c.from, c.epoch)),
            Some((Stage::Forward, 2))
        );
        assert_eq!((stages.stage(), stages.number()), (Stage::Finished, 2));
        let status = stages.status();
        assert!(status.finished());
        assert_eq!(
            (
                status.curriculum_stage,
                status.epoch,
                status.stage_1_end_env_steps
            ),
            (Stage::Forward, 2, Some(500))
        );
        assert_eq!(stages.end_stage_1(1000), None);
    }

    #[test]
    fn stage_only_options() {
        let mut stages = StageMachine::new(StagePlan::ForwardOnly);
        assert_eq!(stages.stage(), Stage::Forward);
        assert_eq!(stages.stage_1_end_env_steps(), Some(0));
        assert_eq!(stages.end_stage_1(10), None);

        let mut stages = StageMachine::new(StagePlan::ReverseOnly);
        assert_eq!(stages.end_stage_1(10).map(|c| c.to), Some(Stage::Finished));
        assert_eq!(stages.epoch(), 1);

        let both = TrainConfig {
            stage_1_only: true,
            stage_2_only: true,
            ..TrainConfig::default()
        };
        let err = both.stage_plan().unwrap_err().to_string();
        assert!(err.contains("train.stage_2_only"), "{err}");
    }

    #[test]
    fn a_resumed_run_follows_the_plan_it_resumes_under() {
        // Stopped at the end of stage 1 under stage_1_only: resumed without it, stage 2 begins
        // in a new epoch, and stage 1's end is kept.
        let mut stages = StageMachine::new(StagePlan::ReverseOnly);
        stages.end_stage_1(1000);
        assert_eq!(
            stages.replan(StagePlan::Both, 1010),
            Ok(Some(StageChange {
                from: Stage::Finished,
                to: Stage::Forward,
                epoch: 2,
                env_steps: 1010
            }))
        );
        assert_eq!(stages.status().curriculum_stage, Stage::Forward);
        assert_eq!(stages.stage_1_end_env_steps(), Some(1000));
        assert_eq!(stages.replan(StagePlan::Both, 1020), Ok(None));
        assert_eq!(stages.finish(2000).map(|c| c.from), Some(Stage::Forward));

        // Forward-only after stage 1 ended under stage_1_only: the same.
        let mut stages = StageMachine::new(StagePlan::ReverseOnly);
        stages.end_stage_1(1000);
        let change = stages.replan(StagePlan::ForwardOnly, 1000).unwrap();
        assert_eq!(change.map(|c| c.to), Some(Stage::Forward));

        // Finished in stage 1 by the stop rule (stage 1 never ended): stays finished.
        let mut stages = StageMachine::new(StagePlan::Both);
        stages.finish(500);
        assert_eq!(stages.replan(StagePlan::Both, 500), Ok(None));
        assert!(stages.status().finished());

        // In stage 1, resumed with stage_1_only: the end of stage 1 ends the run.
        let mut stages = StageMachine::new(StagePlan::Both);
        assert_eq!(stages.replan(StagePlan::ReverseOnly, 100), Ok(None));
        assert_eq!(stages.end_stage_1(300).map(|c| c.to), Some(Stage::Finished));

        // Past stage 1, resumed with stage_1_only: refused, in stage 2 or finished in it.
        let mut stages = StageMachine::new(StagePlan::Both);
        stages.end_stage_1(300);
        assert_eq!(
            stages.replan(StagePlan::ReverseOnly, 400),
            Err(ReplanError::Stage1OnlyInStage2)
        );
        stages.finish(500);
        assert_eq!(
            stages.replan(StagePlan::ReverseOnly, 500),
            Err(ReplanError::Stage1OnlyInStage2)
        );

        // Finished in stage 2 by the stop rule: stays finished under either other plan.
        for plan in [StagePlan::Both, StagePlan::ForwardOnly] {
            let before = stages.clone();
            assert_eq!(stages.replan(plan, 500), Ok(None));
            assert_eq!(stages, before);
        }

        // A snapshot from before `finished_in` (it could only finish at the end of stage 1).
        let mut stages = StageMachine::new(StagePlan::ReverseOnly);
        stages.end_stage_1(1000);
        let mut json = serde_json::to_value(&stages).unwrap();
        json.as_object_mut().unwrap().remove("finished_in");
        let mut stages: StageMachine = serde_json::from_value(json).unwrap();
        let change = stages.replan(StagePlan::Both, 1000).unwrap();
        assert_eq!(change.map(|c| c.to), Some(Stage::Forward));

        // In stage 1, resumed forward-only: refused, the machine unchanged.
        let mut stages = StageMachine::new(StagePlan::Both);
        let before = stages.clone();
        assert_eq!(
            stages.replan(StagePlan::ForwardOnly, 100),
            Err(ReplanError::ForwardOnlyInStage1)
        );
        assert_eq!(stages, before);
    }
}
