//! The run's state as the curriculum server tells other processes (`GetState`): the contract the
//! launcher's progress and summary and `rfcl demos select` read, kept apart from the dashboard's
//! view so that a page can change without touching them. The dashboard's view embeds it. Fields
//! added after the first release default when absent, so the state of an older server still reads.
use serde::{Deserialize, Serialize};

/// The curriculum side of a run: stage, counts, per-demo progress and evaluations.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RunState {
    pub run_name: String,
    pub env_id: String,
    pub stage: u32,
    pub stage_epoch: u64,
    /// The run is over: nothing more is handed out (the stop rule, or stage 1 under
    /// `stage_1_only`).
    #[serde(default)]
    pub finished: bool,
    /// Env steps reported by train episodes.
    pub env_steps: u64,
    pub stage_1_env_steps: Option<u64>,
    pub episodes: u64,
    pub expired_leases: u64,
    /// Simulator worker restarts over all actors and their respawns (a restarted worker replays
    /// its episode, so nothing else shows it).
    #[serde(default)]
    pub sim_worker_restarts: u64,
    /// Leases an actor could not reset its env to, over the run (per demo in `demos`).
    #[serde(default)]
    pub failed_resets: u64,
    pub refused_reports: RefusedReports,
    /// Success rate of the last train episodes, as of the newest progress sample.
    #[serde(default)]
    pub train_success_rate: Option<f64>,
    pub demos: Vec<DemoBar>,
    pub evals: Vec<EvalPoint>,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RefusedReports {
    pub duplicate: u64,
    pub expired: u64,
    pub unknown: u64,
    pub epoch_mismatch: u64,
    pub malformed: u64,
    /// From an actor that does not hold the lease (refused PERMISSION_DENIED).
    #[serde(default)]
    pub not_holder: u64,
    /// Episodes longer than their lease's time limit (refused INVALID_ARGUMENT).
    #[serde(default)]
    pub over_time_limit: u64,
}

impl RefusedReports {
    /// Reports refused for any reason.
    pub fn total(&self) -> u64 {
        self.duplicate
            + self.expired
            + self.unknown
            + self.epoch_mismatch
            + self.malformed
            + self.not_holder
            + self.over_time_limit
    }
}

/// One demo's reverse-curriculum progress (spec 2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DemoBar {
    pub demo: u32,
    /// The demo's episode id in the demo file (the run may have shuffled or picked a subset).
    /// Absent from older servers' JSON.
    #[serde(default)]
    pub episode_id: u64,
    /// Current start step t_i.
    pub t: u32,
    /// States kept, S_i.
    pub states: u32,
    /// Fraction of successes in the demo's frontier FIFO.
    pub frontier_success_rate: f64,
    pub solved: bool,
    /// How hard this demo is (docs/ALGORITHM.md 2.10). Absent from older servers' JSON.
    #[serde(default)]
    pub difficulty: DemoDifficulty,
}

/// One demo's stage-1 difficulty: its frontier's history and speed, how episodes from it fare, and
/// whether it has stalled while the others advance (docs/ALGORITHM.md 2.10).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DemoDifficulty {
    /// Stage-1 episodes started from this demo, and their share of all stage-1 episodes.
    pub episodes: u64,
    pub episode_share: f64,
    /// Episodes started at the frontier t_i, and the success rate of all of them.
    pub frontier_episodes: u64,
    pub frontier_success_rate: f64,
    /// States the frontier moved back per 10,000 env steps (until solved).
    pub speed: f64,
    /// Env steps since the frontier last moved (0 once solved).
    pub env_steps_since_move: u64,
    /// Env steps when the demo became solved.
    pub solved_env_steps: Option<u64>,
    /// Flagged: not solved, and no move for `service.stall_after_env_steps` env steps while
    /// another demo's frontier moved. It stalls at its current t_i.
    pub stalled: bool,
    /// On PointMaze, the maze cell `[row, col]` of the state at t_i (where it stalls, if it does).
    pub cell: Option<[u32; 2]>,
    /// `[env steps, t_i]` after each move of the frontier, oldest first.
    pub frontier: Vec<[u64; 2]>,
    /// Leases of this demo whose reset failed in the actor, and the last one's state index and
    /// reason. Absent from older servers' JSON.
    #[serde(default)]
    pub failed_resets: u64,
    #[serde(default)]
    pub last_reset_failure: Option<(u32, String)>,
}

/// Eval outcomes of one policy version.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalPoint {
    pub policy_version: u64,
    pub env_steps: u64,
    pub episodes: u64,
    pub success_at_end: f64,
    pub success_once: f64,
    pub mean_return: f64,
}

/// A sample of progress over time, taken by the service every few seconds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProgressPoint {
    pub wall_s: f64,
    pub env_steps: u64,
    pub stage: u32,
    /// Mean of t_i / (S_i - 1): 1 at the start of stage 1, 0 when every demo starts from its beginning.
    pub start_step_frac_avg: f64,
    pub solved_frac: f64,
    pub train_success_rate: f64,
}
