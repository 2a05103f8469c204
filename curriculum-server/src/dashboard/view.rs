//! The dashboard's view model: everything the page, `/api/state` and `/metrics` show, as plain
//! serialisable data. Fields added after the first release default when absent, so the JSON of an
//! older server still reads.
use rfcl_core::video::VideoMeta;
use serde::{Deserialize, Serialize};

pub use rfcl_core::run_state::{
    DemoBar, DemoDifficulty, EvalPoint, ProgressPoint, RefusedReports, RunState,
};

/// Everything the dashboard shows; `/api/state` serves it as JSON.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DashboardView {
    /// What other processes read too (`GetState`), flattened into the page's JSON.
    #[serde(flatten)]
    pub run: RunState,
    pub episodes_per_s: f64,
    pub open_leases: u64,
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
    pub levels: Vec<LevelRow>,
    pub actors: Vec<ActorRow>,
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
