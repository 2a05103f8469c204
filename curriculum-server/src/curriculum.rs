//! The curriculum as the server runs it: the reverse and forward curricula, the stage machine and
//! one seeded random stream. `acquire` hands out resets and `report` applies finished episodes. The
//! whole state, random stream included, serialises, so a restored snapshot continues exactly.
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::{RunConfig, StagePlan};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::difficulty::Difficulty;
use crate::forward::{Forward, LevelSource};
use crate::reverse::{DemoMeta, ReportEffect, Reverse};
use crate::stage::{ReplanError, Stage, StageChange, StageMachine};

#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum CurriculumError {
    #[error("the curriculum needs at least one demo")]
    NoDemos,
    #[error("the forward curriculum has no levels (forward.num_seeds is 0 and no demo starts)")]
    NoLevels,
    #[error("invalid curriculum config: {0}")]
    InvalidConfig(String),
    #[error("unknown demo {demo} (there are {count})")]
    UnknownDemo { demo: usize, count: usize },
    #[error("unknown level {level} (there are {count})")]
    UnknownLevel { level: usize, count: usize },
    #[error("a {kind} assignment cannot be reported in stage {stage:?}")]
    WrongStage { kind: &'static str, stage: Stage },
    #[error(
        "the run is finished (stage 1 ended under train.stage_1_only, or the evaluations reached \
         service.stop_at_eval_success)"
    )]
    Finished,
    #[error(transparent)]
    Replan(#[from] ReplanError),
    #[error(
        "the config changes {} since the run's snapshot, but {why}; resume with the values in the \
         run's config.yml, or start a new run for the new ones",
        changes.join(", ")
    )]
    ChangedOnResume {
        changes: Vec<String>,
        why: &'static str,
    },
}

/// What [`Curriculum::resume_under`] changed.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Resumed {
    /// Set when the new stage plan moved the run on (a `stage_1_only` run into stage 2).
    pub stage_change: Option<StageChange>,
    /// `forward.<field>: old -> new` for each forward option taken over from the new config.
    pub forward_adopted: Vec<String>,
    /// `reverse.<field>: old -> new` for each reverse option that changed after stage 1 ended:
    /// without effect, since the reverse curriculum is not used again.
    pub reverse_ignored: Vec<String>,
    /// `env.max_episode_steps: old -> new` when the horizon changed after stage 1 ended: stage-2
    /// episodes end at the new one.
    pub horizon_adopted: Option<String>,
}

/// Where an episode starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum AssignmentKind {
    /// Stage 1: state `start_index` of demo `demo`, after resetting with the demo's reset arguments.
    DemoState { demo: usize, start_index: usize },
    /// Stage 2: forward-curriculum level `level`.
    Level { level: usize, source: LevelSource },
}

/// One reset handed to an actor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Assignment {
    pub kind: AssignmentKind,
    /// Steps after which the episode is truncated (already capped by the env horizon).
    pub time_limit: u32,
    pub stage_epoch: u64,
}

/// What a finished episode reports to the curriculum.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EpisodeOutcome {
    /// The success flag at the final step (stage 1 counts this, spec 2.6).
    pub success_at_end: bool,
    /// The episode's return (stage 2 scores this, spec 3.3).
    pub episode_return: f64,
}

/// How a report was applied.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Applied {
    /// The assignment belongs to an earlier stage epoch: ignored.
    Stale,
    Reverse(ReportEffect),
    Forward {
        level: usize,
        score: f64,
    },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReportOutcome {
    pub applied: Applied,
    /// Set when this report ended stage 1.
    pub stage_change: Option<StageChange>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Curriculum {
    reverse: Reverse,
    forward: Forward,
    stages: StageMachine,
    /// Per-demo stage-1 history (docs/ALGORITHM.md 2.10); absent in older snapshots.
    #[serde(default)]
    difficulty: Difficulty,
    /// H: the env horizon, the time limit of every stage-2 episode.
    horizon: u32,
    rng: ChaCha8Rng,
}

impl Curriculum {
    /// A fresh curriculum for `demos`, its random stream seeded with the experiment seed.
    pub fn new(config: &RunConfig, demos: &[DemoMeta]) -> Result<Self, CurriculumError> {
        let horizon = config.env.max_episode_steps;
        Ok(Self {
            reverse: Reverse::new(config.reverse.clone(), demos, horizon)?,
            forward: Forward::new(config.forward_curriculum(), demos)?,
            stages: StageMachine::new(stage_plan(config)?),
            difficulty: Difficulty::default(),
            horizon,
            rng: ChaCha8Rng::seed_from_u64(config.seed),
        })
    }

    /// The next reset: a demo state in stage 1, a level in stage 2.
    pub fn acquire(&mut self) -> Result<Assignment, CurriculumError> {
        let (kind, time_limit) = match self.stages.stage() {
            Stage::Reverse => {
                let choice = self.reverse.sample(&mut self.rng);
                let kind = AssignmentKind::DemoState {
                    demo: choice.demo,
                    start_index: choice.start_index,
                };
                (kind, choice.time_limit)
            }
            Stage::Forward => {
                let level = self.forward.sample(&mut self.rng);
                let source = self.forward.levels()[level].source;
                (AssignmentKind::Level { level, source }, self.horizon)
            }
            Stage::Finished => return Err(CurriculumError::Finished),
        };
        Ok(Assignment {
            kind,
            time_limit,
            stage_epoch: self.stages.epoch(),
        })
    }

    /// Applies the outcome of an episode run from `assignment`; `env_steps` is the run's env-step
    /// count now (this episode's included), recorded if this report ends stage 1 (spec 2.7,
    /// checked after every report) and in the per-demo history.
    pub fn report(
        &mut self,
        assignment: &Assignment,
        outcome: EpisodeOutcome,
        env_steps: u64,
    ) -> Result<ReportOutcome, CurriculumError> {
        if assignment.stage_epoch != self.stages.epoch() {
            return Ok(ReportOutcome {
                applied: Applied::Stale,
                stage_change: None,
            });
        }
        let stage = self.stages.stage();
        match (assignment.kind, stage) {
            (AssignmentKind::DemoState { demo, start_index }, Stage::Reverse) => {
                let effect = self
                    .reverse
                    .report(demo, start_index, outcome.success_at_end)?;
                self.difficulty.record(
                    demo,
                    outcome.success_at_end,
                    &effect,
                    self.reverse.demos(),
                    env_steps,
                );
                let stage_change = if self.reverse.stage_1_done() {
                    self.stages.end_stage_1(env_steps)
                } else {
                    None
                };
                Ok(ReportOutcome {
                    applied: Applied::Reverse(effect),
                    stage_change,
                })
            }
            (AssignmentKind::Level { level, .. }, Stage::Forward) => {
                let score = self.forward.report(level, outcome.episode_return)?;
                Ok(ReportOutcome {
                    applied: Applied::Forward { level, score },
                    stage_change: None,
                })
            }
            (AssignmentKind::DemoState { .. }, _) => Err(CurriculumError::WrongStage {
                kind: "demo-state",
                stage,
            }),
            (AssignmentKind::Level { .. }, _) => Err(CurriculumError::WrongStage {
                kind: "level",
                stage,
            }),
        }
    }

    pub fn reverse(&self) -> &Reverse {
        &self.reverse
    }

    pub fn difficulty(&self) -> &Difficulty {
        &self.difficulty
    }

    pub fn forward(&self) -> &Forward {
        &self.forward
    }

    /// Ends the run (the stop rule, [`crate::stop`]).
    pub fn finish(&mut self, env_steps: u64) -> Option<StageChange> {
        self.stages.finish(env_steps)
    }

    /// Brings a restored curriculum in line with the config the run resumes under: its stage plan
    /// ([`StageMachine::replan`]) and its curriculum options. A forward curriculum that has not
    /// begun is rebuilt under the new `forward` options (a stage-1 checkpoint can go on into
    /// stage 2 under several variants). Once stage 2 has begun its scores and staleness come
    /// from the old options, so changing them is refused, as is changing `reverse` or the env
    /// horizon in stage 1 (every stage-1 time limit is capped by it). After stage 1 the reverse
    /// curriculum is history: changed `reverse` options are reported, not applied, and a new
    /// horizon is the time limit of the stage-2 episodes from now on. Nothing changes when an
    /// error is returned.
    pub fn resume_under(
        &mut self,
        config: &RunConfig,
        demos: &[DemoMeta],
        env_steps: u64,
    ) -> Result<Resumed, CurriculumError> {
        let forward = config.forward_curriculum();
        let forward_changes = changed_fields("forward", self.forward.config(), &forward);
        let reverse_changes = changed_fields("reverse", self.reverse.config(), &config.reverse);
        let horizon = config.env.max_episode_steps;
        let horizon_change = (horizon != self.horizon)
            .then(|| format!("env.max_episode_steps: {} -> {horizon}", self.horizon));
        if !forward_changes.is_empty() && self.stages.forward_started() {
            return Err(CurriculumError::ChangedOnResume {
                changes: forward_changes,
                why: "stage 2 has begun and its level scores were built under the old values",
            });
        }
        if self.stages.stage() == Stage::Reverse
            && (!reverse_changes.is_empty() || horizon_change.is_some())
        {
            return Err(CurriculumError::ChangedOnResume {
                changes: reverse_changes.into_iter().chain(horizon_change).collect(),
                why: "the run is in stage 1 and its reverse curriculum was built under the old \
                      values",
            });
        }
        let rebuilt = if forward_changes.is_empty() {
            None
        } else {
            Some(Forward::new(forward, demos)?)
        };
        // `replan` leaves the machine as it was when it refuses.
        let stage_change = self.stages.replan(stage_plan(config)?, env_steps)?;
        if let Some(rebuilt) = rebuilt {
            self.forward = rebuilt;
        }
        self.horizon = horizon;
        Ok(Resumed {
            stage_change,
            forward_adopted: forward_changes,
            reverse_ignored: reverse_changes,
            horizon_adopted: horizon_change,
        })
    }

    pub fn stages(&self) -> &StageMachine {
        &self.stages
    }
}

fn stage_plan(config: &RunConfig) -> Result<StagePlan, CurriculumError> {
    config
        .train
        .stage_plan()
        .map_err(|e| CurriculumError::InvalidConfig(e.to_string()))
}

/// `section.field: old -> new` for every top-level field of two configs of one type that differs.
fn changed_fields<T: Serialize>(section: &str, old: &T, new: &T) -> Vec<String> {
    let as_object = |config: &T| match serde_json::to_value(config) {
        Ok(serde_json::Value::Object(fields)) => fields,
        _ => unreachable!("curriculum configs serialise to JSON objects"),
    };
    let (old, new) = (as_object(old), as_object(new));
    old.iter()
        .filter(|(field, value)| new.get(*field) != Some(*value))
        .map(|(field, value)| {
            let now = new.get(field).cloned().unwrap_or(serde_json::Value::Null);
            format!("{section}.{field}: {value} -> {now}")
        })
        .collect()
}
