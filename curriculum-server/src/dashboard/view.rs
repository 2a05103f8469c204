//! The dashboard's view model: everything the page, `/api/state` and `/metrics` show, as plain
//! serialisable data. Fields added after the first release default when absent, so the JSON of an
//! older server still reads.
use rfcl_core::video::VideoMeta;
use serde::{Deserialize, Serialize};

/// Everything the dashboard shows; `/api/state` serves it as JSON.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DashboardView {
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
    pub episodes_per_s: f64,
    pub open_leases: u64,
    pub expired_leases: u64,
    /// Simulator worker restarts over all actors and their respawns (a restarted worker replays
    /// its episode, so nothing else shows it). Absent from older servers' JSON.
    #[serde(default)]
    pub sim_worker_restarts: u64,
    /// Leases an actor could not reset its env to, over the run (per demo in `demos`). Absent
    /// from older servers' JSON.
    #[serde(default)]
    pub failed_resets: u64,
    pub refused_reports: RefusedReports,
    /// Calls refused UNAUTHENTICATED (no run token or a wrong one) since the server started.
    #[serde(default)]
    pub unauthenticated_calls: u64,
    /// Calls refused OUT_OF_RANGE for a request over the server's message limit since it started.
    #[serde(default)]
    pub oversized_requests: u64,
    /// Dashboard connections closed at once for being over the dashboard's bound.
    #[serde(default)]
    pub dashboard_refused: u64,
    /// Actor ids dropped from `actors` after `service.forget_actors_after_s` without a call.
    #[serde(default)]
    pub actors_forgotten: u64,
    /// Snapshot writes that failed since the server started (each is logged; the server stops
    /// after several failures in a row).
    #[serde(default)]
    pub snapshot_failures: u64,
    pub solved_frac: f64,
    pub demos: Vec<DemoBar>,
    pub levels: Vec<LevelRow>,
    pub actors: Vec<ActorRow>,
    pub evals: Vec<EvalPoint>,
    pub history: Vec<ProgressPoint>,
    /// The PointMaze success heatmap (PointMaze runs only).
    #[serde(default)]
    pub maze: Option<MazeView>,
    /// The learner as its Health RPC last answered; `None` until a learner announces where it
    /// serves. Absent from older servers' JSON.
    #[serde(default)]
    pub learner: Option<LearnerPanel>,
    /// Eval episodes recorded by eval actors (`eval_env.video_every`), by policy version.
    #[serde(default)]
    pub videos: Vec<VideoLink>,
    /// Videos refused (malformed, no run directory, a failed write).
    #[serde(default)]
    pub videos_refused: u64,
    /// Old videos removed to make room for newer ones (the per-actor and byte bounds).
    #[serde(default)]
    pub videos_evicted: u64,
}

/// An eval video the server keeps, and where the dashboard serves it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VideoLink {
    #[serde(flatten)]
    pub meta: VideoMeta,
    /// `/videos/<file name>` on the dashboard.
    pub url: String,
}

impl From<VideoMeta> for VideoLink {
    fn from(meta: VideoMeta) -> Self {
        VideoLink {
            url: format!("/videos/{}", meta.file_name()),
            meta,
        }
    }
}

/// The learner beside the curriculum, polled over gRPC (its Health RPC, with the run's token).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LearnerPanel {
    /// Where the learner said it serves (`learner --advertise`).
    pub address: String,
    /// Seconds since the learner last answered; `None`: it has not answered yet.
    pub seconds_since_answer: Option<f64>,
    /// Why the last poll failed, when it did.
    pub error: Option<String>,
    /// False once the learner's training thread failed (its own flag), or while its last poll
    /// went unanswered.
    pub ok: bool,
    pub env_steps: u64,
    pub critic_updates: u64,
    pub policy_version: u64,
    /// The learner session (it changes when the learner restarts).
    pub run_id: String,
    /// Its last progress window; `None` before the first (the first ten seconds).
    pub window: Option<LearnerWindowView>,
}

/// One progress window of the learner: rates, losses, and where its time went.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LearnerWindowView {
    pub seconds: f64,
    pub updates_per_s: f64,
    pub env_steps_per_s: f64,
    /// Critic updates per env step since the start, and the configured ratio.
    pub utd: f64,
    pub utd_target: f64,
    /// How many versions behind the newest policy the oldest acting policy was.
    pub policy_lag_max: u64,
    /// Means over the window's updates; `None` when no update ran in it.
    pub critic_loss: Option<f64>,
    pub actor_loss: Option<f64>,
    pub q: Option<f64>,
    pub entropy: Option<f64>,
    pub temperature: Option<f64>,
    /// Fractions of the window spent waiting for data, taking it in, updating, publishing the
    /// policy and checkpointing (the rest is the loop's own bookkeeping).
    pub time_shares: TimeShares,
}

/// Fractions of a window per learner activity.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct TimeShares {
    pub waiting: f64,
    pub ingesting: f64,
    pub updating: f64,
    pub publishing: f64,
    pub checkpointing: f64,
}

impl TimeShares {
    /// `(label, fraction)` in display order.
    pub fn labelled(&self) -> [(&'static str, f64); 5] {
        [
            ("updating", self.updating),
            ("waiting for data", self.waiting),
            ("taking in data", self.ingesting),
            ("publishing the policy", self.publishing),
            ("checkpointing", self.checkpointing),
        ]
    }
}

/// The PointMaze heatmap (the paper's figure): success per start cell over the run.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MazeView {
    /// The layout, one string per row (`#` wall, `X` hazard wall, `G` goal, `.` open), as in
    /// `rfcl_core::maze::MAP`.
    pub map: Vec<String>,
    /// Evals spread over the run, oldest first; the last is the latest complete eval.
    pub snapshots: Vec<MazeSnapshot>,
    /// Per demo, the point's `(x, y)` at every step (x = column, y = row).
    pub demo_paths: Vec<Vec<[f32; 2]>>,
}

/// Eval success per start cell of one policy version.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MazeSnapshot {
    pub policy_version: u64,
    pub env_steps: u64,
    pub success_rate: f64,
    pub cells: Vec<MazeCell>,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MazeCell {
    pub row: u32,
    pub col: u32,
    pub episodes: u64,
    pub successes: u64,
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

/// One forward-curriculum level (spec 3).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LevelRow {
    pub level: u32,
    /// "seed 12" or "demo 3 start".
    pub label: String,
    pub score: f64,
    pub staleness: u64,
    pub probability: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActorRow {
    pub actor_id: u32,
    pub seconds_since_seen: f64,
    pub env_steps: u64,
    pub episodes: u64,
    pub open_leases: u64,
    /// Simulator worker restarts of this actor id over all its processes.
    #[serde(default)]
    pub sim_restarts: u64,
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
