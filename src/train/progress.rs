//! The pure bookkeeping of `rfcl train`: which evaluations are complete, when the run may stop
//! early, and the run summary (docs/DESIGN.md, "Run directory": steps and wall time to each
//! success threshold, stage-1 length, final success rates). No I/O: the orchestrator feeds it the
//! curriculum server's state and the wall clock.
use std::collections::BTreeMap;

use rfcl_core::config::eval_point;
use rfcl_core::final_counters::LearnerCounts;
use rfcl_core::run_state::{DemoBar, EvalPoint, RefusedReports, RunState};
use serde::{Deserialize, Serialize};

/// Evals whose running mean decides an early stop (`service.stop_at_eval_success`; the curriculum
/// server applies the rule).
pub use rfcl_curriculum::stop::STOP_WINDOW;
/// Success thresholds reported in the summary.
pub const THRESHOLDS: [f64; 2] = [0.5, 0.9];

/// One complete evaluation (spec 5.7): the curriculum server's eval point (a policy version, the
/// learner's env steps when it was published, its outcomes over all its episodes) once it has
/// all its episodes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CompleteEval {
    #[serde(flatten)]
    pub point: EvalPoint,
    /// Run wall time (over every session of the run) at which `rfcl train` saw it complete.
    pub wall_s: f64,
}

/// What a run keeps across sessions (`RUN_DIR/train_progress.json`): the wall time of earlier
/// sessions and when each eval completed, so that a resumed run's summary counts wall time
/// from the run's start.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RunProgress {
    /// Wall seconds of the sessions before this one.
    pub earlier_sessions_s: f64,
    /// Wall seconds of the current session as of its last save. A session that ends cleanly folds
    /// them into `earlier_sessions_s`; one that was killed (SIGKILL, a machine restart) leaves
    /// them here and the next session folds them in, so its time is not lost.
    #[serde(default)]
    pub session_s: f64,
    pub sessions: u32,
    pub evals: Vec<CompleteEval>,
    pub actor_respawns: u64,
    /// Every restart of the learner or the curriculum server, in order.
    #[serde(default)]
    pub restarts: Vec<ServiceRestart>,
    /// Transition records the learners of the sessions so far took in but never used because
    /// their session stopped first (each clean stop's `learner_final.json`).
    #[serde(default)]
    pub unused_records: u64,
}

/// A service that died and was restarted from its last checkpoint or snapshot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ServiceRestart {
    /// `learner` or `curriculum-server`.
    pub process: String,
    /// Run wall time of the death.
    pub wall_s: f64,
    /// How it ended ("killed by signal 9", "exit status 1").
    pub cause: String,
    /// What the restart lost: the learner's env steps and updates since its last checkpoint, or
    /// the curriculum's episode reports since its last snapshot (their leases' episodes happened,
    /// but the curriculum no longer counts them).
    pub rolled_back: RolledBack,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RolledBack {
    pub env_steps: u64,
    pub updates: u64,
    pub reports: u64,
}

impl RolledBack {
    /// What went from `before` (last seen before the death) to `after` (first seen after the
    /// restart): the counters that went backwards, by how much.
    pub fn between(before: [u64; 3], after: [u64; 3]) -> Self {
        let lost = |i: usize| before[i].saturating_sub(after[i]);
        Self {
            env_steps: lost(0),
            updates: lost(1),
            reports: lost(2),
        }
    }
}

impl RunProgress {
    /// Starts a session: counts it and takes in the time a killed session left behind.
    pub fn begin_session(&mut self) {
        self.earlier_sessions_s += std::mem::take(&mut self.session_s);
        self.sessions += 1;
    }

    /// What to save while the session runs, `session_s` into it.
    pub fn during_session(&self, session_s: f64) -> RunProgress {
        RunProgress {
            session_s,
            ..self.clone()
        }
    }

    /// What to save when the session ends cleanly after `session_s`.
    pub fn after_session(&self, session_s: f64) -> RunProgress {
        RunProgress {
            earlier_sessions_s: self.earlier_sessions_s + session_s,
            session_s: 0.0,
            ..self.clone()
        }
    }
}

/// Tracks evaluations as the curriculum server aggregates them.
#[derive(Debug, Clone)]
pub struct EvalTracker {
    episodes_needed: u64,
    complete: BTreeMap<u64, CompleteEval>,
}

impl EvalTracker {
    /// An evaluation is complete once `episodes_needed` episodes of it were reported.
    pub fn new(episodes_needed: u64, earlier: &[CompleteEval]) -> Self {
        Self {
            episodes_needed: episodes_needed.max(1),
            complete: earlier
                .iter()
                .map(|e| (e.point.policy_version, e.clone()))
                .collect(),
        }
    }

    /// Takes the server's eval points; returns the ones that became complete, stamped `wall_s`.
    pub fn update(&mut self, points: &[EvalPoint], wall_s: f64) -> Vec<CompleteEval> {
        let mut fresh = Vec::new();
        for p in points {
            if p.episodes < self.episodes_needed || self.complete.contains_key(&p.policy_version) {
                continue;
            }
            let eval = CompleteEval {
                point: p.clone(),
                wall_s,
            };
            self.complete.insert(p.policy_version, eval.clone());
            fresh.push(eval);
        }
        fresh
    }

    /// Complete evals in env-step order.
    pub fn evals(&self) -> Vec<CompleteEval> {
        let mut all: Vec<CompleteEval> = self.complete.values().cloned().collect();
        all.sort_by_key(|e| (e.point.env_steps, e.point.policy_version));
        all
    }

    /// Mean success-at-end of the last [`STOP_WINDOW`] complete evals, once there are that many.
    pub fn running_mean(&self) -> Option<f64> {
        let rates: Vec<f64> = self
            .evals()
            .iter()
            .map(|e| e.point.success_at_end)
            .collect();
        rfcl_curriculum::stop::running_mean(&rates)
    }

    /// Wilson 95 % interval of the success-at-end rate over the episodes of the last
    /// [`STOP_WINDOW`] complete evals pooled, once there are that many: how far the stop rule's
    /// mean may be from the policy's own success rate (10-episode evals are noisy).
    pub fn running_interval(&self) -> Option<[f64; 2]> {
        let evals = self.evals();
        (evals.len() >= STOP_WINDOW).then(|| {
            let window = &evals[evals.len() - STOP_WINDOW..];
            let episodes: u64 = window.iter().map(|e| e.point.episodes).sum();
            let successes: f64 = window
                .iter()
                .map(|e| e.point.success_at_end * e.point.episodes as f64)
                .sum();
            wilson_interval(successes, episodes, Z_95)
        })
    }

    /// Whether the run reached `service.stop_at_eval_success`.
    pub fn reached(&self, stop_at: Option<f64>) -> bool {
        match (stop_at, self.running_mean()) {
            (Some(bar), Some(mean)) => mean >= bar,
            _ => false,
        }
    }

    /// The first complete eval (by env steps) whose success-at-end reached `threshold`.
    pub fn first_reaching(&self, threshold: f64) -> Option<CompleteEval> {
        self.evals()
            .into_iter()
            .find(|e| e.point.success_at_end >= threshold)
    }

    pub fn last(&self) -> Option<CompleteEval> {
        self.evals().pop()
    }

    /// Whether an evaluation of the final policy, published at `env_steps`, is still to come: its
    /// evaluation point (spec 5.7) is past the newest complete evaluation's.
    pub fn final_eval_pending(&self, env_steps: u64, eval_freq: u64, num_seed_steps: u64) -> bool {
        let point = |steps| eval_point(steps, eval_freq, num_seed_steps);
        let evaluated = self
            .last()
            .and_then(|e| point(e.point.env_steps))
            .unwrap_or(0);
        point(env_steps).is_some_and(|p| p > evaluated)
    }
}

/// The standard normal quantile of a two-sided 95 % interval.
const Z_95: f64 = 1.959_963_985;

/// Wilson score interval of a binomial rate: `successes` of `n` trials, normal quantile `z`.
/// Unlike the normal approximation it stays inside [0, 1] and is sound near 0 % and 100 %.
pub fn wilson_interval(successes: f64, n: u64, z: f64) -> [f64; 2] {
    if n == 0 {
        return [0.0, 1.0];
    }
    let n = n as f64;
    let p = successes / n;
    let z2n = z * z / n;
    let center = (p + z2n / 2.0) / (1.0 + z2n);
    let half = z / (1.0 + z2n) * (p * (1.0 - p) / n + z2n / (4.0 * n)).sqrt();
    [(center - half).max(0.0), (center + half).min(1.0)]
}

/// When the run reached a success threshold.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Milestone {
    pub threshold: f64,
    pub env_steps: Option<u64>,
    pub wall_s: Option<f64>,
    pub policy_version: Option<u64>,
}

/// How a session ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Ending {
    /// The learner used the step budget (`train.steps`) and exited.
    Budget,
    /// Stage 1 ended and the config stops there (`train.stage_1_only`).
    #[serde(rename = "stage_1_done")]
    Stage1Done,
    /// The running mean of the last evals reached `service.stop_at_eval_success`.
    EvalSuccess,
    /// Ctrl-C or SIGTERM: resume with `--resume`.
    Interrupted,
    /// A process failed beyond what supervision repairs (the summary's `error` says which).
    Failed,
}

/// `RUN_DIR/summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub run_name: String,
    pub env_id: String,
    pub ending: Ending,
    /// Why the run failed, when `ending` is `failed`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Env steps the learner received (its Health), and its critic updates.
    pub env_steps: u64,
    /// `final`: the learner's counters below are its own when it stopped, from one moment.
    /// `last_poll`: it wrote none (killed); they are its last Health reply, with env steps
    /// raised to at least the last eval's, and the transport counts can trail them by a few
    /// batches.
    #[serde(default)]
    pub learner_counters: CountersSource,
    pub updates: u64,
    pub policy_version: u64,
    pub wall_s: f64,
    pub sessions: u32,
    /// Env steps when stage 1 ended (the curriculum's `stage_1_env_steps`), if it did.
    pub stage_1_env_steps: Option<u64>,
    pub stage: u32,
    /// Env steps and wall time to 50 % and 90 % eval success (success at the end, spec 5.7).
    pub to_success: Vec<Milestone>,
    pub final_eval: Option<CompleteEval>,
    pub eval_success_mean_last_5: Option<f64>,
    /// Wilson 95 % interval over the last 5 evals' episodes pooled.
    #[serde(default)]
    pub eval_success_last_5_ci95: Option<[f64; 2]>,
    /// Success at the end of the last 100 training episodes.
    pub train_success_rate: Option<f64>,
    /// The curriculum server's counters: train episodes and their env steps, leases.
    pub curriculum_episodes: u64,
    pub curriculum_env_steps: u64,
    pub expired_leases: u64,
    pub refused_reports: u64,
    /// The same by reason (duplicate, expired, unknown lease, stage epoch mismatch, malformed,
    /// not the lease holder, longer than the lease's time limit).
    #[serde(default)]
    pub refused_reports_by_reason: RefusedReports,
    pub actor_respawns: u64,
    /// Restarts of the learner and the curriculum server, with what each rolled back.
    #[serde(default)]
    pub service_restarts: Vec<ServiceRestart>,
    /// Simulator worker processes restarted after a crash or hang (the curriculum server's count
    /// over all actors and their respawns); each replayed its episode, so nothing else shows it.
    #[serde(default)]
    pub sim_worker_restarts: u64,
    /// Leases an actor could not reset its env to (the episode never ran; per demo with the last
    /// reason in `demos`).
    #[serde(default)]
    pub failed_resets: u64,
    /// Transition records the learner took in per transport (its Health; the last session's
    /// learner process): same-host actors use shared memory, remote ones gRPC.
    #[serde(default)]
    pub transitions_shm: u64,
    #[serde(default)]
    pub transitions_grpc: u64,
    /// Records missing between an actor's shared-memory frames, and batches refused as
    /// malformed (the last session's learner process).
    #[serde(default)]
    pub transitions_lost_shm: u64,
    #[serde(default)]
    pub refused_batches: u64,
    /// Why `env_steps` (the learner's) and `curriculum_env_steps` differ, and whether the counted
    /// losses explain the difference.
    #[serde(default)]
    pub env_steps_accounting: StepAccounting,
    pub evals: Vec<CompleteEval>,
    /// Per demo: where its reverse-curriculum frontier ended and how hard it was (speed, stall
    /// flag; docs/ALGORITHM.md 2.10). `rfcl demos select` reads it.
    #[serde(default)]
    pub demos: Vec<DemoBar>,
}

/// The two services count env steps independently: the learner the transition records it
/// received, the curriculum server the lengths of the train episodes reported to it. They differ,
/// and each difference has a counted cause:
///
/// * either has more by the episodes in flight when both were read: running, not yet reported
///   (the learner has more), or reported before the learner stored their last records (the
///   curriculum has more); at most one per train env, each at most `horizon` steps;
/// * the learner has more by the episodes whose report never counted (expired leases, refused
///   reports, reports lost when the curriculum server rolled back to its snapshot), each at most
///   `horizon` steps;
/// * the curriculum has more by the steps the learner lost when it rolled back to its
///   checkpoint, the records lost between shared-memory frames or in refused batches, the records
///   the learner dropped because their stage epoch had ended, and those it took in but never
///   used because a session stopped first.
///
/// `explained` says whether the difference lies within those bounds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StepAccounting {
    /// `env_steps - curriculum_env_steps`.
    pub learner_minus_curriculum: i64,
    /// Steps of episodes in flight when both counts were read: train envs × horizon, at most.
    pub in_flight_at_most: u64,
    /// Train episodes whose report the curriculum does not count: expired leases, refused reports
    /// and reports rolled back by curriculum-server restarts.
    pub unreported_episodes: u64,
    /// Env steps the learner rolled back over all its restarts.
    pub learner_rolled_back: u64,
    /// Records lost between shared-memory frames, and batches refused whole.
    pub lost_records: u64,
    pub refused_batches: u64,
    /// Records the learner received but did not store: their stage epoch had ended, or a session
    /// stopped before it used them.
    #[serde(default)]
    pub dropped_stale_epoch: u64,
    #[serde(default)]
    pub unused_records: u64,
    pub explained: bool,
}

impl StepAccounting {
    /// Compares the two counts with the bounds [`UncountedSteps`] gives each side.
    pub fn new(learner_env_steps: u64, curriculum_env_steps: u64, counts: UncountedSteps) -> Self {
        let restarts = counts.restarts;
        let learner_rolled_back = restarts
            .iter()
            .filter(|r| r.process == "learner")
            .map(|r| r.rolled_back.env_steps)
            .sum::<u64>();
        let reports_rolled_back = restarts
            .iter()
            .filter(|r| r.process == "curriculum-server")
            .map(|r| r.rolled_back.reports)
            .sum::<u64>();
        let unreported_episodes =
            counts.expired_leases + counts.refused_reports + reports_rolled_back;
        let in_flight_at_most = counts.train_envs * counts.horizon;
        let more_in_learner = in_flight_at_most + unreported_episodes * counts.horizon;
        let more_in_curriculum = in_flight_at_most
            + learner_rolled_back
            + counts.lost_records
            + counts.refused_batches * counts.batch_records
            + counts.dropped_stale_epoch
            + counts.unused_records;
        let difference = learner_env_steps as i64 - curriculum_env_steps as i64;
        Self {
            learner_minus_curriculum: difference,
            in_flight_at_most,
            unreported_episodes,
            learner_rolled_back,
            lost_records: counts.lost_records,
            refused_batches: counts.refused_batches,
            dropped_stale_epoch: counts.dropped_stale_epoch,
            unused_records: counts.unused_records,
            explained: -(more_in_curriculum as i64) <= difference
                && difference <= more_in_learner as i64,
        }
    }
}

/// What [`StepAccounting::new`] needs besides the two counts.
#[derive(Debug, Clone, Copy)]
pub struct UncountedSteps<'a> {
    pub train_envs: u64,
    /// The most steps one episode has.
    pub horizon: u64,
    /// The most records one refused batch had.
    pub batch_records: u64,
    pub expired_leases: u64,
    pub refused_reports: u64,
    pub lost_records: u64,
    pub refused_batches: u64,
    pub dropped_stale_epoch: u64,
    pub unused_records: u64,
    pub restarts: &'a [ServiceRestart],
}

/// Which Health reply a summary's learner counters come from.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CountersSource {
    /// The learner's own counts when it stopped (`learner_final.json`): every counter is from
    /// that one moment, so the transport counts cover the env steps.
    Final,
    /// The learner wrote none (it was killed): its last periodic Health reply, which can trail
    /// the run's end by a few batches.
    #[default]
    LastPoll,
}

/// The learner's counters as `rfcl train` last saw them, all from one moment.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LearnerCounters {
    pub source: CountersSource,
    pub counts: LearnerCounts,
}

/// What a run's summary needs from its config.
#[derive(Debug, Clone, Copy)]
pub struct RunShape {
    /// Train envs over all actors.
    pub train_envs: u64,
    /// The longest a train episode can run.
    pub horizon: u64,
    /// The most records one transition batch carries.
    pub batch_records: u64,
}

/// Builds the summary of a run from its trackers and the curriculum server's last state.
pub fn summarize(
    view: &RunState,
    evals: &EvalTracker,
    learner: LearnerCounters,
    progress: &RunProgress,
    shape: RunShape,
    wall_s: f64,
    ending: Ending,
) -> Summary {
    // Without the learner's final answer the last periodic one can predate its last steps, while
    // each eval carries the learner's count when it published the evaluated policy: the learner
    // received at least that many. Only then are env steps raised past the reply's own, and the
    // summary says so (`learner_counters: last_poll`); a final reply is taken as it is.
    let mut counts = learner.counts;
    if let (CountersSource::LastPoll, Some(last)) = (learner.source, evals.last()) {
        counts.env_steps = counts.env_steps.max(last.point.env_steps);
        counts.policy_version = counts.policy_version.max(last.point.policy_version);
    }
    let env_steps_accounting = StepAccounting::new(
        counts.env_steps,
        view.env_steps,
        UncountedSteps {
            train_envs: shape.train_envs,
            horizon: shape.horizon,
            batch_records: shape.batch_records,
            expired_leases: view.expired_leases,
            refused_reports: view.refused_reports.total(),
            lost_records: counts.shm_lost_records,
            refused_batches: counts.refused_batches,
            dropped_stale_epoch: counts.dropped_stale_epoch,
            unused_records: progress.unused_records,
            restarts: &progress.restarts,
        },
    );
    let to_success = THRESHOLDS
        .iter()
        .map(|&threshold| {
            let hit = evals.first_reaching(threshold);
            Milestone {
                threshold,
                env_steps: hit.as_ref().map(|e| e.point.env_steps),
                wall_s: hit.as_ref().map(|e| e.wall_s),
                policy_version: hit.as_ref().map(|e| e.point.policy_version),
            }
        })
        .collect();
    Summary {
        run_name: view.run_name.clone(),
        env_id: view.env_id.clone(),
        ending,
        error: None,
        env_steps: counts.env_steps,
        learner_counters: learner.source,
        updates: counts.updates,
        policy_version: counts.policy_version,
        wall_s,
        sessions: progress.sessions,
        stage_1_env_steps: view.stage_1_env_steps,
        stage: view.stage,
        to_success,
        final_eval: evals.last(),
        eval_success_mean_last_5: evals.running_mean(),
        eval_success_last_5_ci95: evals.running_interval(),
        train_success_rate: view.train_success_rate,
        curriculum_episodes: view.episodes,
        curriculum_env_steps: view.env_steps,
        expired_leases: view.expired_leases,
        refused_reports: view.refused_reports.total(),
        refused_reports_by_reason: view.refused_reports,
        actor_respawns: progress.actor_respawns,
        service_restarts: progress.restarts.clone(),
        sim_worker_restarts: view.sim_worker_restarts,
        failed_resets: view.failed_resets,
        transitions_shm: counts.shm_records,
        transitions_grpc: counts.grpc_records,
        transitions_lost_shm: counts.shm_lost_records,
        refused_batches: counts.refused_batches,
        env_steps_accounting,
        evals: evals.evals(),
        demos: view.demos.clone(),
    }
}

/// `total` envs split over `parts` processes as evenly as possible (the first ones get one more).
pub fn split_envs(total: u32, parts: u32) -> Vec<u32> {
    (0..parts)
        .map(|i| total / parts + u32::from(i < total % parts))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(version: u64, env_steps: u64, episodes: u64, success: f64) -> EvalPoint {
        EvalPoint {
            policy_version: version,
            env_steps,
            episodes,
            success_at_end: success,
            success_once: success,
            mean_return: success * 10.0,
        }
    }

    #[test]
    fn evals_complete_once_with_enough_episodes() {
        let mut t = EvalTracker::new(10, &[]);
        assert!(t.update(&[point(3, 3000, 4, 0.0)], 1.0).is_empty());
        let fresh = t.update(&[point(3, 3000, 10, 0.2), point(5, 5000, 9, 1.0)], 2.0);
        assert_eq!(fresh.len(), 1);
        assert_eq!((fresh[0].point.policy_version, fresh[0].wall_s), (3, 2.0));
        // Seen again (more episodes): not new, and the recorded time stays.
        assert!(t.update(&[point(3, 3000, 12, 0.3)], 3.0).is_empty());
        assert_eq!(t.evals()[0].wall_s, 2.0);
    }

    #[test]
    fn the_final_policy_is_awaited_only_when_it_passed_an_eval_point_not_yet_evaluated() {
        let mut t = EvalTracker::new(1, &[]);
        // No eval yet: due once past the seed steps and the first multiple.
        assert!(
            !t.final_eval_pending(900, 1000, 500),
            "before the first point"
        );
        assert!(
            !t.final_eval_pending(1500, 1000, 2000),
            "inside the seed steps"
        );
        assert!(t.final_eval_pending(1000, 1000, 500));
        t.update(&[point(40, 1008, 5, 0.0)], 1.0);
        // 1008 covers the point 1000: a final policy at 1999 passed no new one; at 2000 it did.
        assert!(!t.final_eval_pending(1999, 1000, 500));
        assert!(t.final_eval_pending(2000, 1000, 500));
        t.update(&[point(80, 2000, 5, 0.5)], 2.0);
        assert!(!t.final_eval_pending(2000, 1000, 500), "already evaluated");
    }

    #[test]
    fn early_stop_needs_five_evals_whose_mean_reaches_the_bar() {
        let mut t = EvalTracker::new(1, &[]);
        let successes = [0.0, 0.6, 1.0, 1.0, 1.0, 0.9, 1.0];
        for (i, s) in successes.iter().enumerate() {
            t.update(
                &[point(i as u64 + 1, 1000 * (i as u64 + 1), 5, *s)],
                i as f64,
            );
            let expected = match i {
                0..=3 => None,
                4 => Some((0.0 + 0.6 + 3.0) / 5.0),
                5 => Some((0.6 + 3.0 + 0.9) / 5.0),
                _ => Some((3.0 + 0.9 + 1.0) / 5.0),
            };
            let mean = t.running_mean();
            assert_eq!(mean.is_some(), expected.is_some(), "eval {i}");
            if let (Some(m), Some(e)) = (mean, expected) {
                assert!((m - e).abs() < 1e-12, "eval {i}: {m} vs {e}");
            }
        }
        assert!(t.reached(Some(0.9)));
        assert!(!t.reached(Some(0.99)));
        assert!(!t.reached(None));
        let first90 = t.first_reaching(0.9).unwrap();
        assert_eq!(
            (first90.point.policy_version, first90.point.env_steps),
            (3, 3000)
        );
        assert_eq!(t.first_reaching(0.5).unwrap().point.policy_version, 2);
    }

    #[test]
    fn a_resumed_tracker_keeps_earlier_evals_and_their_times() {
        let earlier = vec![CompleteEval {
            point: EvalPoint {
                success_once: 1.0,
                mean_return: 3.0,
                ..point(2, 2000, 10, 0.95)
            },
            wall_s: 42.0,
        }];
        let mut t = EvalTracker::new(10, &earlier);
        assert!(t.update(&[point(2, 2000, 10, 0.95)], 100.0).is_empty());
        assert_eq!(t.first_reaching(0.9).unwrap().wall_s, 42.0);
    }

    #[test]
    fn wilson_interval_matches_a_hand_computed_case() {
        // 46 of 50 at z = 1.96: p = 0.92, z²/n = 0.076832, centre 0.958416 / 1.076832 = 0.890033,
        // half-width 1.96 / 1.076832 * sqrt(0.92 * 0.08 / 50 + 0.076832 / 200) = 0.078418.
        let [lo, hi] = wilson_interval(46.0, 50, 1.96);
        assert!((lo - 0.811615).abs() < 1e-6, "{lo}");
        assert!((hi - 0.968451).abs() < 1e-6, "{hi}");
        // All successes: the upper end is 1, the lower n / (n + z²).
        let [lo, hi] = wilson_interval(10.0, 10, 1.96);
        assert!((lo - 10.0 / 13.8416).abs() < 1e-12 && hi == 1.0);
        assert_eq!(wilson_interval(0.0, 0, 1.96), [0.0, 1.0]);
    }

    #[test]
    fn the_running_interval_pools_the_last_five_evals_episodes() {
        let mut t = EvalTracker::new(10, &[]);
        let points: Vec<EvalPoint> = [0.0, 0.8, 1.0, 1.0, 0.8, 1.0]
            .iter()
            .enumerate()
            .map(|(i, &s)| point(i as u64 + 1, 1000 * (i as u64 + 1), 10, s))
            .collect();
        t.update(&points, 1.0);
        // The last five: 46 of 50.
        let [lo, hi] = t.running_interval().unwrap();
        let [elo, ehi] = wilson_interval(46.0, 50, Z_95);
        assert!((lo - elo).abs() < 1e-12 && (hi - ehi).abs() < 1e-12);
        assert!(lo < 0.92 && 0.92 < hi);
        assert!(EvalTracker::new(10, &[]).running_interval().is_none());
    }

    #[test]
    fn a_killed_sessions_wall_time_is_kept_for_the_next() {
        let mut p = RunProgress::default();
        p.begin_session();
        // A clean session of 100 s, then one killed 40 s in (its last save said 30 s).
        let mut p: RunProgress = p.after_session(100.0);
        p.begin_session();
        let saved = p.during_session(30.0);
        assert_eq!((saved.earlier_sessions_s, saved.session_s), (100.0, 30.0));
        let mut resumed: RunProgress =
            serde_json::from_str(&serde_json::to_string(&saved).unwrap()).unwrap();
        resumed.begin_session();
        assert_eq!(
            (
                resumed.earlier_sessions_s,
                resumed.session_s,
                resumed.sessions
            ),
            (130.0, 0.0, 3)
        );
        // Files written before the field existed still read.
        let old: RunProgress = serde_json::from_str(
            r#"{"earlier_sessions_s": 5.0, "sessions": 1, "evals": [], "actor_respawns": 0}"#,
        )
        .unwrap();
        assert_eq!(old.session_s, 0.0);
    }

    #[test]
    fn summary_reports_milestones_and_counters() {
        let mut t = EvalTracker::new(2, &[]);
        t.update(
            &[
                point(1, 1000, 2, 0.1),
                point(2, 2000, 2, 0.55),
                point(3, 3000, 2, 0.92),
            ],
            7.0,
        );
        let view: RunState = serde_json::from_value(serde_json::json!({
            "run_name": "r", "env_id": "PointMaze-v0", "stage": 2, "stage_epoch": 1,
            "env_steps": 2900, "stage_1_env_steps": 1500, "episodes": 100,
            "expired_leases": 4, "sim_worker_restarts": 2, "failed_resets": 5,
            "refused_reports": {"duplicate": 1, "expired": 2, "unknown": 0, "epoch_mismatch": 3, "malformed": 0},
            "train_success_rate": 0.75, "demos": [], "evals": [],
        }))
        .unwrap();
        let progress = RunProgress {
            sessions: 2,
            actor_respawns: 1,
            unused_records: 30,
            ..RunProgress::default()
        };
        let learner = LearnerCounters {
            source: CountersSource::Final,
            counts: LearnerCounts {
                env_steps: 3100,
                updates: 1550,
                policy_version: 40,
                shm_records: 3000,
                grpc_records: 100,
                shm_lost_records: 7,
                refused_batches: 1,
                dropped_stale_epoch: 5,
                // This session's, already in `progress.unused_records` with the earlier ones'.
                unused_records: 20,
            },
        };
        let shape = RunShape {
            train_envs: 2,
            horizon: 10,
            batch_records: 64,
        };
        let s = summarize(&view, &t, learner, &progress, shape, 60.0, Ending::Budget);
        assert_eq!(s.stage_1_env_steps, Some(1500));
        assert_eq!((s.transitions_shm, s.transitions_grpc), (3000, 100));
        assert_eq!((s.transitions_lost_shm, s.refused_batches), (7, 1));
        assert_eq!(s.to_success[0].env_steps, Some(2000));
        assert_eq!(s.to_success[1].env_steps, Some(3000));
        assert_eq!(s.to_success[1].wall_s, Some(7.0));
        assert_eq!(s.final_eval.as_ref().unwrap().point.policy_version, 3);
        assert_eq!(s.eval_success_mean_last_5, None);
        assert_eq!(s.train_success_rate, Some(0.75));
        assert_eq!((s.expired_leases, s.refused_reports), (4, 6));
        assert_eq!((s.env_steps, s.updates, s.actor_respawns), (3100, 1550, 1));
        let json = serde_json::to_value(&s).unwrap();
        assert_eq!(json["ending"], "budget");
        assert_eq!(json["sim_worker_restarts"], 2);
        assert_eq!(json["failed_resets"], 5);
        assert_eq!(json["to_success"][1]["threshold"], 0.9);
        // 3100 - 2900 = 200 more in the learner; at most 2 × 10 in flight and (4 expired + 6
        // refused) × 10 unreported: 120 explained, so 200 is not.
        let a = s.env_steps_accounting;
        assert_eq!((a.learner_minus_curriculum, a.in_flight_at_most), (200, 20));
        assert_eq!(a.unreported_episodes, 10);
        assert!(!a.explained);
        assert_eq!((a.dropped_stale_epoch, a.unused_records), (5, 30));
        assert_eq!(json["learner_counters"], "final");
        // A final reply is taken as it is: its transport counts and env steps are one moment's.
        let final_reply = LearnerCounters {
            counts: LearnerCounts {
                env_steps: 2950,
                shm_records: 2900,
                grpc_records: 50,
                ..learner.counts
            },
            ..learner
        };
        let s = summarize(
            &view,
            &t,
            final_reply,
            &progress,
            shape,
            60.0,
            Ending::EvalSuccess,
        );
        assert_eq!((s.env_steps, s.transitions_shm), (2950, 2900));
        assert_eq!(s.learner_counters, CountersSource::Final);
        // Only a periodic poll, older than the last eval's policy: the learner had received at
        // least the env steps that policy carries, so no milestone lies beyond the summary's env
        // steps, and the summary says its transport counts may trail them.
        let stale = LearnerCounters {
            source: CountersSource::LastPoll,
            counts: LearnerCounts {
                env_steps: 2950,
                ..learner.counts
            },
        };
        let s = summarize(
            &view,
            &t,
            stale,
            &progress,
            shape,
            60.0,
            Ending::EvalSuccess,
        );
        assert_eq!((s.env_steps, s.policy_version), (3000, 40));
        assert_eq!(
            serde_json::to_value(&s).unwrap()["learner_counters"],
            "last_poll"
        );
        assert!(s
            .to_success
            .iter()
            .all(|m| m.env_steps <= Some(s.env_steps)));
        assert_eq!(json["env_steps_accounting"]["explained"], false);
    }

    #[test]
    fn step_accounting_bounds_each_side_by_its_counted_causes() {
        let restart = |process: &str, env_steps, reports| ServiceRestart {
            process: process.into(),
            wall_s: 1.0,
            cause: "killed by signal 9".into(),
            rolled_back: RolledBack {
                env_steps,
                updates: 0,
                reports,
            },
        };
        let restarts = [
            restart("learner", 500, 0),
            restart("curriculum-server", 0, 3),
        ];
        let counts = UncountedSteps {
            train_envs: 8,
            horizon: 50,
            batch_records: 64,
            expired_leases: 2,
            refused_reports: 1,
            lost_records: 10,
            refused_batches: 1,
            dropped_stale_epoch: 0,
            unused_records: 0,
            restarts: &restarts,
        };
        // Learner side: 8 × 50 in flight + (2 + 1 + 3) × 50 unreported = 700.
        assert!(StepAccounting::new(10_700, 10_000, counts).explained);
        assert!(!StepAccounting::new(10_701, 10_000, counts).explained);
        // Curriculum side: 400 in flight + 500 rolled back + 10 lost + 1 × 64 refused = 974.
        let a = StepAccounting::new(10_000, 10_974, counts);
        assert!(a.explained);
        assert_eq!(
            (a.learner_minus_curriculum, a.learner_rolled_back),
            (-974, 500)
        );
        assert_eq!(a.unreported_episodes, 6);
        assert!(!StepAccounting::new(10_000, 10_975, counts).explained);
        // Records the learner received and did not store count on the curriculum's side too:
        // 974 + 1,088 stale + 320 unused = 2,382 (a run interrupted in stage 2).
        let counts = UncountedSteps {
            dropped_stale_epoch: 1_088,
            unused_records: 320,
            ..counts
        };
        let a = StepAccounting::new(10_000, 12_382, counts);
        assert!(a.explained);
        assert_eq!((a.dropped_stale_epoch, a.unused_records), (1_088, 320));
        assert!(!StepAccounting::new(10_000, 12_383, counts).explained);
        // They do not widen the learner's side.
        assert!(!StepAccounting::new(10_701, 10_000, counts).explained);
    }

    #[test]
    fn restarts_say_what_they_rolled_back() {
        // The learner came back at its checkpoint: 2,000 env steps and 500 updates lost; the
        // reports counter is not the learner's and did not move.
        assert_eq!(
            RolledBack::between([12_000, 3_000, 7], [10_000, 2_500, 7]),
            RolledBack {
                env_steps: 2_000,
                updates: 500,
                reports: 0
            }
        );
        // Counters that grew in between (a restart after new work) lose nothing.
        assert_eq!(
            RolledBack::between([5, 5, 5], [6, 5, 9]),
            RolledBack::default()
        );
    }

    #[test]
    fn envs_split_evenly() {
        assert_eq!(split_envs(8, 2), [4, 4]);
        assert_eq!(split_envs(8, 3), [3, 3, 2]);
        assert_eq!(split_envs(4, 1), [4]);
    }
}
