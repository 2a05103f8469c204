//! The curriculum server's state and its transitions: the pure [`Curriculum`], the lease table
//! that makes reports exactly-once, and the counters the dashboard shows.
//!
//! Everything that changes curriculum state happens here, on a [`ServerState`] that the service
//! keeps under one mutex: this process is the single writer. The state speaks domain types only
//! (core's leases and reports, the curriculum's [`StageStatus`]); the gRPC layer converts them to
//! and from the wire.
use std::collections::{BTreeMap, VecDeque};
use std::time::{SystemTime, UNIX_EPOCH};

use rfcl_core::config::RunConfig;
use rfcl_core::demo::DemoSet;
use rfcl_core::lease::{AcquireRequest, EpisodeReport, LeaseKind, ResetArgs, ResetLease};
use serde::{Deserialize, Serialize};

use crate::leases::{LeaseTable, ReportClaim, ReportRefusal};
use crate::{
    stop, Applied, Assignment, AssignmentKind, Curriculum, CurriculumError, DemoMeta,
    EpisodeOutcome, LevelSource, StageStatus,
};
use rfcl_core::run_state::ProgressPoint;

/// Seconds since the Unix epoch: lease times survive a restart from a snapshot.
pub fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// What the server needs of each demo to build leases: its reset states and reset arguments.
#[derive(Debug, Clone)]
pub struct DemoResets {
    pub state_dim: usize,
    /// Per demo, the flat states [S_i_total, state_dim].
    pub states: Vec<Vec<f32>>,
    pub reset: Vec<ResetArgs>,
    /// Per demo, its episode id in the demo file (the run may have shuffled or picked a subset).
    pub episode_ids: Vec<u64>,
}

impl DemoResets {
    pub fn from_demos(demos: &DemoSet) -> Self {
        DemoResets {
            state_dim: demos.state_dim,
            states: demos.demos.iter().map(|d| d.env_states.clone()).collect(),
            reset: demos.demos.iter().map(|d| d.reset.clone()).collect(),
            episode_ids: demos.demos.iter().map(|d| d.episode_id).collect(),
        }
    }

    pub(crate) fn state(&self, demo: usize, index: usize) -> Vec<f32> {
        self.states[demo][index * self.state_dim..(index + 1) * self.state_dim].to_vec()
    }

    /// The PointMaze cell `[row, col]` of a demo's state (spec 7.5: states start with the point's
    /// `(x, y)`).
    pub fn maze_cell(&self, demo: usize, index: usize) -> Option<[u32; 2]> {
        let start = index.checked_mul(self.state_dim)?;
        let s = self.states.get(demo)?.get(start..start + 2)?;
        let (row, col) = rfcl_core::maze::cell_at([s[0], s[1]])?;
        Some([row as u32, col as u32])
    }
}

/// The curricula's view of the demos.
pub fn demo_metas(demos: &DemoSet) -> Vec<DemoMeta> {
    demos
        .demos
        .iter()
        .map(|d| DemoMeta {
            success: d.success.clone(),
            reset_seed: d.reset.seed,
        })
        .collect()
}

/// What a lease was handed out for.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Granted {
    Train(Assignment),
    Eval { seed: u64 },
}

/// Eval outcomes of one policy version (spec 5.7), keyed by version and env steps.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct EvalAggregate {
    pub env_steps: u64,
    pub episodes: u64,
    pub success_at_end: u64,
    pub success_once: u64,
    pub return_sum: f64,
    /// `(reset seed, success at the end)` of every episode, for per-start views such as the
    /// PointMaze heatmap (a seed determines the start cell). Absent in older snapshots.
    #[serde(default)]
    pub outcomes: Vec<(u64, bool)>,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ActorStats {
    pub last_seen: f64,
    pub env_steps: u64,
    pub episodes: u64,
    /// Simulator worker restarts of this actor id over all its processes: a restarted worker
    /// replays its episode and leaves no other trace. Absent in older snapshots.
    #[serde(default)]
    pub sim_restarts: u64,
    /// The last restart count this actor id reported (its current process's count).
    #[serde(default)]
    pub last_reported_sim_restarts: u64,
}

impl ActorStats {
    /// Takes a report's restart heartbeat, which counts the reporting process's restarts: growth
    /// is new restarts; a value below the last one comes from a respawned actor process, which
    /// counts from 0 again, so all of it is new.
    pub fn record_sim_restarts(&mut self, reported: u64) {
        self.sim_restarts += reported
            .checked_sub(self.last_reported_sim_restarts)
            .unwrap_or(reported);
        self.last_reported_sim_restarts = reported;
    }
}

/// Counters and history: everything the dashboard shows beyond the curriculum itself.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    pub env_steps: u64,
    pub episodes: u64,
    pub malformed_reports: u64,
    pub next_eval_seed: u64,
    /// success_at_end of the last 100 train episodes.
    pub recent_success: VecDeque<bool>,
    pub evals: BTreeMap<u64, EvalAggregate>,
    pub actors: BTreeMap<u32, ActorStats>,
    pub history: Vec<ProgressPoint>,
    pub started_at: f64,
    /// (time, episodes) of the previous history sample, for episodes/s.
    pub last_sample: (f64, u64),
    pub episodes_per_s: f64,
    /// Actor ids dropped from `actors` after `service.forget_actors_after_s` without a call.
    /// Absent in older snapshots.
    #[serde(default)]
    pub actors_forgotten: u64,
    /// Simulator worker restarts of the forgotten actors: the run's total keeps them.
    #[serde(default)]
    pub forgotten_sim_restarts: u64,
    /// Leases an actor could not reset its env to (a demo state the simulator refused), per demo
    /// and for leases of no demo. Absent in older snapshots.
    #[serde(default)]
    pub failed_resets: FailedResets,
}

/// Leases whose reset failed in the actor: the episode never ran, the curriculum's outcome
/// statistics are untouched, and the run goes on.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FailedResets {
    /// Per demo id: how many, and the last one's start state and reason.
    pub per_demo: BTreeMap<u32, DemoResetFailures>,
    /// Eval leases and seed levels (no demo state).
    pub other: u64,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DemoResetFailures {
    pub count: u64,
    pub last_start_index: u32,
    pub last_reason: String,
}

impl FailedResets {
    pub fn total(&self) -> u64 {
        self.other + self.per_demo.values().map(|d| d.count).sum::<u64>()
    }

    fn record(&mut self, granted: &Granted, reason: &str) {
        let demo = match granted {
            Granted::Train(a) => match a.kind {
                AssignmentKind::DemoState { demo, start_index } => Some((demo, start_index)),
                AssignmentKind::Level {
                    source: LevelSource::DemoStart { demo, .. },
                    ..
                } => Some((demo, 0)),
                AssignmentKind::Level { .. } => None,
            },
            Granted::Eval { .. } => None,
        };
        match demo {
            Some((demo, start_index)) => {
                let d = self.per_demo.entry(demo as u32).or_default();
                d.count += 1;
                d.last_start_index = start_index as u32;
                d.last_reason = reason.to_owned();
            }
            None => self.other += 1,
        }
    }
}

impl Stats {
    /// Simulator worker restarts of the whole run, over every actor and its respawns.
    pub fn sim_worker_restarts(&self) -> u64 {
        self.forgotten_sim_restarts + self.actors.values().map(|a| a.sim_restarts).sum::<u64>()
    }
}

const RECENT_EPISODES: usize = 100;
const MAX_HISTORY: usize = 2000;

/// The whole mutable state of the server; it is also what a snapshot holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ServerState {
    pub curriculum: Curriculum,
    pub leases: LeaseTable<Granted>,
    pub stats: Stats,
    /// Reports applied since the last snapshot.
    #[serde(skip)]
    pub reports_since_snapshot: u64,
}

/// A report's effect, for the RPC answer.
#[derive(Debug, Clone, PartialEq)]
pub struct ReportResult {
    pub applied: bool,
    /// Where the run stands, when the report changed the stage.
    pub stage_change: Option<StageStatus>,
    /// The report closed an EVAL lease (the stop rule may apply).
    pub eval: bool,
}

/// Why a report changed nothing.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error(transparent)]
    Refused(#[from] ReportRefusal),
    #[error("lease {lease_id} is from stage epoch {lease_epoch}, which ended; the stage epoch is now {now}")]
    StageEpochOver {
        lease_id: u64,
        lease_epoch: u64,
        now: u64,
    },
    #[error(transparent)]
    Curriculum(#[from] CurriculumError),
}

impl ServerState {
    pub fn new(curriculum: Curriculum, now: f64) -> Self {
        let stats = Stats {
            started_at: now,
            last_sample: (now, 0),
            ..Default::default()
        };
        let mut state = ServerState {
            curriculum,
            leases: LeaseTable::new(100_000),
            stats,
            reports_since_snapshot: 0,
        };
        state.sample_history(now);
        state
    }

    /// Ends the run when its evaluations reached `service.stop_at_eval_success` ([`stop`]);
    /// returns where the run stands once ended.
    pub fn apply_stop_rule(&mut self, cfg: &RunConfig) -> Option<StageStatus> {
        let needed = rfcl_core::config::episodes_per_eval(cfg);
        if !stop::reached(&self.stats.evals, needed, cfg.service.stop_at_eval_success) {
            return None;
        }
        let change = self.curriculum.finish(self.stats.env_steps)?;
        tracing::info!(
            env_steps = change.env_steps,
            bar = cfg.service.stop_at_eval_success,
            "the last {} evaluations reached service.stop_at_eval_success: the run is finished",
            stop::STOP_WINDOW
        );
        Some(self.stage_status())
    }

    /// Where the run stands: what every report's answer and every stage watcher is told.
    pub fn stage_status(&self) -> StageStatus {
        self.curriculum.stages().status()
    }

    /// Hands out a lease: a curriculum reset for train actors, a held-out seed for eval actors.
    pub fn acquire(
        &mut self,
        req: AcquireRequest,
        cfg: &RunConfig,
        demos: &DemoResets,
        now: f64,
    ) -> Result<ResetLease, CurriculumError> {
        self.stats.actors.entry(req.actor_id).or_default().last_seen = now;
        let status = self.stage_status();
        if status.finished() {
            return Err(CurriculumError::Finished);
        }
        // Leases are core's type, which carries the stage by its number.
        let (stage, epoch) = (status.number(), status.epoch);
        if req.eval {
            let seed = cfg.eval_env.seed_offset + self.stats.next_eval_seed;
            self.stats.next_eval_seed += 1;
            let grant = self
                .leases
                .grant(req.actor_id, epoch, now, Granted::Eval { seed });
            return Ok(ResetLease {
                lease_id: grant.lease_id,
                kind: LeaseKind::Eval,
                demo_id: 0,
                start_index: 0,
                env_state: Vec::new(),
                // `ResetArgs::default()` holds `{}`; `Value::default()` would be `null`, which
                // is not an options object and fails the lease's wire conversion.
                reset: ResetArgs {
                    seed: Some(seed),
                    ..ResetArgs::default()
                },
                time_limit: eval_time_limit(cfg),
                stage,
                stage_epoch: epoch,
                level: 0,
            });
        }
        let assignment = self.curriculum.acquire()?;
        let lease_id = self
            .leases
            .grant(req.actor_id, epoch, now, Granted::Train(assignment))
            .lease_id;
        let mut lease = ResetLease {
            lease_id,
            kind: LeaseKind::DemoState,
            demo_id: 0,
            start_index: 0,
            env_state: Vec::new(),
            reset: ResetArgs::default(),
            time_limit: assignment.time_limit,
            stage,
            stage_epoch: epoch,
            level: 0,
        };
        match assignment.kind {
            AssignmentKind::DemoState { demo, start_index } => {
                lease.demo_id = demo as u32;
                lease.start_index = start_index as u32;
                lease.env_state = demos.state(demo, start_index);
                lease.reset = demos.reset[demo].clone();
            }
            AssignmentKind::Level { level, source } => {
                lease.kind = LeaseKind::Level;
                lease.level = level as u32;
                match source {
                    LevelSource::Seed(seed) => lease.reset.seed = Some(seed),
                    LevelSource::DemoStart { demo, .. } => {
                        lease.demo_id = demo as u32;
                        lease.env_state = demos.state(demo, 0);
                        lease.reset = demos.reset[demo].clone();
                    }
                }
            }
        }
        Ok(lease)
    }

    /// Applies a report exactly once. A refused report changes nothing but its counter (and, for
    /// a report that does not claim more than its lease allows, the actor's heartbeat).
    pub fn report(
        &mut self,
        report: &EpisodeReport,
        cfg: &RunConfig,
        now: f64,
    ) -> Result<ReportResult, ReportError> {
        let claim = ReportClaim {
            lease_id: report.lease_id,
            stage_epoch: report.stage_epoch,
            actor_id: report.actor_id,
            length: report.length,
        };
        // The episode's steps are added to the run's counts, so they must fit in the lease: the
        // time limit handed out with it (stage 1's dynamic limit, the horizon in stage 2, the
        // eval horizon for eval leases).
        let taken = self.leases.take_for_report(claim, |g| match g.assignment {
            Granted::Train(a) => a.time_limit,
            Granted::Eval { .. } => eval_time_limit(cfg),
        });
        // A report that claims someone else's lease or more steps than its lease allows is not
        // trusted as a heartbeat either.
        if !matches!(
            taken,
            Err(ReportRefusal::NotHolder { .. } | ReportRefusal::OverTimeLimit { .. })
        ) {
            let actor = self.stats.actors.entry(report.actor_id).or_default();
            actor.last_seen = now;
            actor.env_steps = actor.env_steps.max(report.actor_env_steps);
            actor.record_sim_restarts(report.sim_restarts);
        }
        let grant = taken?;
        if let Some(reason) = &report.reset_failure {
            self.stats.failed_resets.record(&grant.assignment, reason);
            self.reports_since_snapshot += 1;
            return Ok(ReportResult {
                applied: true,
                stage_change: None,
                eval: matches!(grant.assignment, Granted::Eval { .. }),
            });
        }
        self.stats
            .actors
            .entry(report.actor_id)
            .or_default()
            .episodes += 1;
        self.reports_since_snapshot += 1;
        let assignment = match grant.assignment {
            Granted::Eval { seed } => {
                let e = self.stats.evals.entry(report.policy_version).or_default();
                e.outcomes.push((seed, report.success_at_end));
                e.env_steps = e.env_steps.max(report.policy_env_steps);
                e.episodes += 1;
                e.success_at_end += report.success_at_end as u64;
                e.success_once += report.success_once as u64;
                e.return_sum += report.episode_return;
                return Ok(ReportResult {
                    applied: true,
                    stage_change: None,
                    eval: true,
                });
            }
            Granted::Train(a) => a,
        };
        let now_epoch = self.curriculum.stages().epoch();
        if assignment.stage_epoch != now_epoch {
            self.leases.refusals.epoch_mismatch += 1;
            return Err(ReportError::StageEpochOver {
                lease_id: report.lease_id,
                lease_epoch: assignment.stage_epoch,
                now: now_epoch,
            });
        }
        self.stats.env_steps += report.length as u64;
        self.stats.episodes += 1;
        self.stats.recent_success.push_back(report.success_at_end);
        if self.stats.recent_success.len() > RECENT_EPISODES {
            self.stats.recent_success.pop_front();
        }
        let outcome = EpisodeOutcome {
            success_at_end: report.success_at_end,
            episode_return: report.episode_return,
        };
        let applied = self
            .curriculum
            .report(&assignment, outcome, self.stats.env_steps)?;
        debug_assert!(
            !matches!(applied.applied, Applied::Stale),
            "epoch checked above"
        );
        Ok(ReportResult {
            applied: true,
            stage_change: applied.stage_change.map(|_| self.stage_status()),
            eval: false,
        })
    }

    /// Drops the actors that have not called for more than `after_s` seconds and hold no open
    /// lease, so the per-actor table (and with it snapshots and GetState) stays bounded however
    /// many actor ids come and go. Their simulator restarts stay in the run's total. An actor that
    /// comes back is listed afresh. Returns how many were dropped.
    pub fn forget_idle_actors(&mut self, now: f64, after_s: f64) -> u64 {
        if !self
            .stats
            .actors
            .values()
            .any(|a| now - a.last_seen > after_s)
        {
            return 0;
        }
        let holders: std::collections::HashSet<u32> =
            self.leases.open_leases().map(|g| g.actor_id).collect();
        let idle: Vec<u32> = self
            .stats
            .actors
            .iter()
            .filter(|(id, a)| now - a.last_seen > after_s && !holders.contains(id))
            .map(|(id, _)| *id)
            .collect();
        for id in &idle {
            if let Some(a) = self.stats.actors.remove(id) {
                self.stats.forgotten_sim_restarts += a.sim_restarts;
            }
        }
        self.stats.actors_forgotten += idle.len() as u64;
        idle.len() as u64
    }

    /// Takes a progress sample for the dashboard's chart (bounded: halves its resolution when full).
    pub fn sample_history(&mut self, now: f64) {
        let (t0, e0) = self.stats.last_sample;
        if now > t0 {
            self.stats.episodes_per_s = (self.stats.episodes - e0) as f64 / (now - t0);
        }
        self.stats.last_sample = (now, self.stats.episodes);
        let reverse = self.curriculum.reverse();
        let point = ProgressPoint {
            wall_s: now - self.stats.started_at,
            env_steps: self.stats.env_steps,
            stage: self.curriculum.stages().number(),
            start_step_frac_avg: reverse.start_step_frac_avg(),
            solved_frac: reverse.solved_frac(),
            train_success_rate: self.train_success_rate(),
        };
        self.stats.history.push(point);
        if self.stats.history.len() > MAX_HISTORY {
            let kept: Vec<_> = self.stats.history.iter().copied().step_by(2).collect();
            self.stats.history = kept;
        }
    }

    /// Success at the end over the last train episodes (at most 100).
    pub(crate) fn train_success_rate(&self) -> f64 {
        let r = &self.stats.recent_success;
        if r.is_empty() {
            0.0
        } else {
            r.iter().filter(|s| **s).count() as f64 / r.len() as f64
        }
    }
}

/// The time limit of every eval episode: the eval env's horizon.
pub fn eval_time_limit(cfg: &RunConfig) -> u32 {
    cfg.eval_env
        .max_episode_steps
        .unwrap_or(cfg.env.max_episode_steps)
}

#[cfg(test)]
mod tests {
    use super::*;
    // Refusals reach actors as gRPC statuses; the codes and messages are part of what is checked.
    use tonic::Status;

    #[test]
    fn sim_worker_restarts_add_up_over_reports_and_respawns() {
        let (cfg, demos, mut state) = one_demo();
        let mut report = |actor_id: u32, sim_restarts: u64| {
            let lease = state
                .acquire(train_request(actor_id), &cfg, &demos, 1.0)
                .unwrap();
            let report = EpisodeReport {
                success_at_end: false,
                success_once: false,
                episode_return: 0.0,
                sim_restarts,
                ..report_of(&lease, actor_id, 1)
            };
            state.report(&report, &cfg, 1.0).unwrap();
        };
        // Actor 1's first process: 2 restarts, then none, then 1 more.
        report(1, 2);
        report(1, 2);
        report(1, 3);
        // Respawned: the new process counts from 0 again and gets to 4.
        report(1, 0);
        report(1, 4);
        // Respawned again, with a restart before its first report.
        report(1, 1);
        report(2, 5);
        assert_eq!(state.stats.actors[&1].sim_restarts, 3 + 4 + 1);
        assert_eq!(state.stats.actors[&2].sim_restarts, 5);
        let view = state.view("run", "PointMaze-v0", 1.0, 50_000);
        assert_eq!(view.run.sim_worker_restarts, 13);
        let rows: Vec<(u32, u64)> = view
            .actors
            .iter()
            .map(|a| (a.actor_id, a.sim_restarts))
            .collect();
        assert_eq!(rows, [(1, 8), (2, 5)]);
        // Snapshots written before the counter existed still load, with 0.
        let old: ActorStats =
            serde_json::from_str(r#"{"last_seen": 1.0, "env_steps": 10, "episodes": 2}"#).unwrap();
        assert_eq!((old.sim_restarts, old.last_reported_sim_restarts), (0, 0));
    }

    fn one_demo() -> (RunConfig, DemoResets, ServerState) {
        let metas = [DemoMeta {
            success: vec![false, false, true],
            reset_seed: Some(0),
        }];
        let cfg = RunConfig::default();
        let demos = DemoResets {
            state_dim: 1,
            // 3 actions, so 4 states.
            states: vec![vec![0.0, 1.0, 2.0, 3.0]],
            reset: vec![ResetArgs::default()],
            episode_ids: vec![0],
        };
        let state = ServerState::new(Curriculum::new(&cfg, &metas).unwrap(), 0.0);
        (cfg, demos, state)
    }

    /// A train actor's request for its env 0.
    fn train_request(actor_id: u32) -> AcquireRequest {
        AcquireRequest {
            actor_id,
            env_index: 0,
            eval: false,
        }
    }

    fn report_of(lease: &ResetLease, actor_id: u32, length: u32) -> EpisodeReport {
        EpisodeReport {
            lease_id: lease.lease_id,
            success_at_end: true,
            success_once: true,
            episode_return: 1.0,
            length,
            policy_version: 0,
            stage_epoch: lease.stage_epoch,
            actor_id,
            actor_env_steps: 5,
            policy_env_steps: 0,
            sim_restarts: 3,
            reset_failure: None,
        }
    }

    #[test]
    fn a_failed_reset_is_counted_against_its_demo_and_changes_no_outcome() {
        let (cfg, demos, mut state) = one_demo();
        let train = train_request(1);
        let failed_report = |lease: &ResetLease, reason: &str| EpisodeReport {
            success_at_end: false,
            success_once: false,
            episode_return: 0.0,
            reset_failure: Some(reason.into()),
            ..report_of(lease, 1, 0)
        };
        let lease = state.acquire(train, &cfg, &demos, 1.0).unwrap();
        let curriculum = state.curriculum.clone();
        let failed = failed_report(&lease, "state field `x` is invalid");
        assert!(state.report(&failed, &cfg, 2.0).unwrap().applied);
        // The lease is closed (a repeat is a duplicate), the outcome statistics untouched.
        assert!(state.report(&failed, &cfg, 2.0).is_err());
        assert_eq!(state.curriculum, curriculum);
        assert_eq!((state.stats.env_steps, state.stats.episodes), (0, 0));
        assert_eq!(state.stats.actors[&1].episodes, 0);
        let view = state.view("run", "PointMaze-v0", 2.0, 50_000);
        assert_eq!(view.run.failed_resets, 1);
        let d = &view.run.demos[0].difficulty;
        assert_eq!(d.failed_resets, 1);
        assert_eq!(
            d.last_reset_failure,
            Some((lease.start_index, "state field `x` is invalid".to_owned()))
        );
        // An eval lease's failure is counted for the run, not a demo.
        let eval = AcquireRequest {
            eval: true,
            ..train
        };
        let lease = state.acquire(eval, &cfg, &demos, 3.0).unwrap();
        state
            .report(&failed_report(&lease, "seed refused"), &cfg, 3.0)
            .unwrap();
        assert_eq!(state.stats.failed_resets.total(), 2);
        assert_eq!(state.stats.failed_resets.other, 1);
        // Snapshots written before the counter existed still load, with none.
        let mut old = serde_json::to_value(&state.stats).unwrap();
        old.as_object_mut().unwrap().remove("failed_resets");
        let old: Stats = serde_json::from_value(old).unwrap();
        assert_eq!(old.failed_resets, FailedResets::default());
    }

    #[test]
    fn reports_longer_than_their_lease_or_from_another_actor_change_nothing() {
        let (cfg, demos, mut state) = one_demo();
        let train = train_request(1);
        let lease = state.acquire(train, &cfg, &demos, 1.0).unwrap();
        let limit = lease.time_limit;
        assert!(limit < cfg.env.max_episode_steps, "stage 1's dynamic limit");
        let before = (state.stats.clone(), state.curriculum.clone());

        let err = state
            .report(&report_of(&lease, 1, u32::MAX), &cfg, 2.0)
            .unwrap_err();
        let status = Status::from(err);
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        assert!(
            status.message().contains("EpisodeReport.length")
                && status.message().contains(&format!("at most {limit}")),
            "{}",
            status.message()
        );
        // One step over the limit is refused too.
        assert!(state
            .report(&report_of(&lease, 1, limit + 1), &cfg, 2.0)
            .is_err());
        let status = Status::from(
            state
                .report(&report_of(&lease, 2, limit), &cfg, 2.0)
                .unwrap_err(),
        );
        assert_eq!(status.code(), tonic::Code::PermissionDenied);
        assert!(
            status.message().contains("EpisodeReport.actor_id")
                && status.message().contains("held by actor 1"),
            "{}",
            status.message()
        );
        // Nothing moved: no env steps, no episode, no actor row for the stranger, no heartbeat.
        assert_eq!((&state.stats, &state.curriculum), (&before.0, &before.1));
        let view = state.view("run", "PointMaze-v0", 2.0, 50_000);
        assert_eq!(
            (
                view.run.refused_reports.over_time_limit,
                view.run.refused_reports.not_holder
            ),
            (2, 1)
        );
        assert_eq!(view.open_leases, 1, "the lease stays open for its holder");
        // The holder's report at the limit applies.
        assert!(
            state
                .report(&report_of(&lease, 1, limit), &cfg, 3.0)
                .unwrap()
                .applied
        );
        assert_eq!(state.stats.env_steps, u64::from(limit));

        // Eval leases are bounded by the eval horizon.
        let eval = AcquireRequest {
            eval: true,
            ..train
        };
        let lease = state.acquire(eval, &cfg, &demos, 4.0).unwrap();
        assert_eq!(lease.time_limit, eval_time_limit(&cfg));
        let status = Status::from(
            state
                .report(&report_of(&lease, 1, lease.time_limit + 1), &cfg, 4.0)
                .unwrap_err(),
        );
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        assert!(
            state
                .report(&report_of(&lease, 1, lease.time_limit), &cfg, 4.0)
                .unwrap()
                .eval
        );
    }

    #[test]
    fn actors_silent_for_too_long_are_forgotten_and_counted() {
        let (cfg, demos, mut state) = one_demo();
        // Actor 1 reports at t = 10 with 3 simulator restarts; actor 2 calls at t = 500; actor 3
        // takes a lease at t = 10 and never reports it.
        let lease = state.acquire(train_request(1), &cfg, &demos, 10.0).unwrap();
        state.report(&report_of(&lease, 1, 1), &cfg, 10.0).unwrap();
        state.acquire(train_request(3), &cfg, &demos, 10.0).unwrap();
        let lease = state
            .acquire(train_request(2), &cfg, &demos, 500.0)
            .unwrap();
        state.report(&report_of(&lease, 2, 1), &cfg, 500.0).unwrap();
        assert_eq!(state.stats.sim_worker_restarts(), 6);

        // At t = 610 actor 1 has been silent for 600 s: not over the bound yet.
        assert_eq!(state.forget_idle_actors(610.0, 600.0), 0);
        // At t = 611 it is; actor 3 is as silent but still holds a lease.
        assert_eq!(state.forget_idle_actors(611.0, 600.0), 1);
        let ids: Vec<u32> = state.stats.actors.keys().copied().collect();
        assert_eq!(ids, [2, 3]);
        // Its restarts stay in the run's total.
        assert_eq!(state.stats.sim_worker_restarts(), 6);
        // Once actor 3's lease expired, it goes too.
        state.leases.expire(611.0, 120.0);
        assert_eq!(state.forget_idle_actors(611.0, 600.0), 1);
        let view = state.view("run", "PointMaze-v0", 611.0, 50_000);
        assert_eq!(view.actors_forgotten, 2);
        assert_eq!(
            view.actors.iter().map(|a| a.actor_id).collect::<Vec<_>>(),
            [2]
        );
        // 10,000 actor ids passing through leave a table of the recent ones only.
        for id in 100..10_100u32 {
            let now = 1000.0 + f64::from(id);
            let lease = state.acquire(train_request(id), &cfg, &demos, now).unwrap();
            state.report(&report_of(&lease, id, 1), &cfg, now).unwrap();
            state.forget_idle_actors(now, 600.0);
        }
        assert!(
            state.stats.actors.len() <= 601,
            "{}",
            state.stats.actors.len()
        );
        // Snapshots of older servers have no counts of forgotten actors.
        let mut old = serde_json::to_value(&state.stats).unwrap();
        let fields = old.as_object_mut().unwrap();
        fields.remove("actors_forgotten");
        fields.remove("forgotten_sim_restarts");
        let old: Stats = serde_json::from_value(old).unwrap();
        assert_eq!((old.actors_forgotten, old.forgotten_sim_restarts), (0, 0));
    }
}
