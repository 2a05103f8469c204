//! The handles a running curriculum server shares between its gRPC service, its dashboard and its
//! background tasks.
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use rfcl_core::config::{RunConfig, Suite};
use rfcl_proto::auth::{ClientAuth, Guard};
use tokio::sync::watch;

use crate::dashboard::DashboardView;
use crate::learner_link::LearnerLink;
use crate::state::{unix_now, DemoResets, ServerState};
use crate::videos::VideoStore;
use crate::StageStatus;

/// Shared handles of a running server.
#[derive(Clone)]
pub struct Shared {
    pub state: Arc<Mutex<ServerState>>,
    pub cfg: Arc<RunConfig>,
    pub demos: Arc<DemoResets>,
    /// Where the run stands, for WatchStage: each stage change replaces it.
    pub stage_tx: Arc<watch::Sender<StageStatus>>,
    /// Signalled when `snapshot_every_reports` reports have been applied since the last snapshot.
    pub snapshot_due: Arc<tokio::sync::Notify>,
    /// The gRPC service's token check: the views count its refusals.
    pub guard: Guard,
    /// Set when the server stops: open WatchStage streams end on it, so a stop never waits on
    /// a subscriber that would otherwise stay forever.
    pub stopping: Arc<watch::Sender<bool>>,
    /// Snapshot writes that failed (the dashboard and /metrics show them).
    pub snapshot_failures: Arc<AtomicU64>,
    /// gRPC requests refused for being over the server's message limit: tonic refuses them
    /// before any handler sees them, so the server's gRPC layer counts them.
    pub oversized_requests: Arc<AtomicU64>,
    /// The learner's announced address and its last Health answer (the learner panel).
    pub learner: Arc<LearnerLink>,
    /// Eval videos sent by eval actors (kept in the run directory).
    pub videos: Arc<VideoStore>,
    /// Dashboard connections closed at once for being over the dashboard's bound
    /// ([`crate::dashboard_listener`]).
    pub dashboard_refused: Arc<AtomicU64>,
}

impl Shared {
    pub fn new(state: ServerState, cfg: RunConfig, demos: DemoResets, guard: Guard) -> Self {
        let (stage_tx, _) = watch::channel(state.stage_status());
        Shared {
            state: Arc::new(Mutex::new(state)),
            cfg: Arc::new(cfg),
            demos: Arc::new(demos),
            stage_tx: Arc::new(stage_tx),
            snapshot_due: Arc::new(tokio::sync::Notify::new()),
            guard,
            stopping: Arc::new(watch::channel(false).0),
            snapshot_failures: Arc::new(AtomicU64::new(0)),
            oversized_requests: Arc::new(AtomicU64::new(0)),
            learner: Arc::new(LearnerLink::new(None)),
            videos: Arc::new(VideoStore::open(None).expect("no directory to list")),
            dashboard_refused: Arc::new(AtomicU64::new(0)),
        }
    }

    /// Polls the learner that announces itself with these credentials (the learner panel).
    pub fn with_learner_auth(self, auth: ClientAuth) -> Self {
        Shared {
            learner: Arc::new(LearnerLink::new(Some(auth))),
            ..self
        }
    }

    /// Keeps eval videos in `store` (the run directory's).
    pub fn with_videos(self, store: VideoStore) -> Self {
        Shared {
            videos: Arc::new(store),
            ..self
        }
    }

    pub fn lock(&self) -> std::sync::MutexGuard<'_, ServerState> {
        self.state
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// The dashboard's view: the state's, with the counters kept outside it (calls refused by the
    /// token check or for their size, failed snapshot writes) and, on PointMaze, the heatmap.
    pub fn view(&self) -> DashboardView {
        let now = unix_now();
        let state = self.lock();
        let mut view = state.view(
            &self.cfg.name,
            &self.cfg.env.env_id,
            now,
            self.cfg.service.stall_after_env_steps,
        );
        view.unauthenticated_calls = self.guard.refused();
        view.snapshot_failures = self.snapshot_failures.load(Ordering::Relaxed);
        view.oversized_requests = self.oversized_requests.load(Ordering::Relaxed);
        view.dashboard_refused = self.dashboard_refused.load(Ordering::Relaxed);
        view.learner = self.learner.panel(now);
        let videos = self.videos.listing();
        view.videos = videos.videos.into_iter().map(Into::into).collect();
        view.videos_refused = videos.refused;
        view.videos_evicted = videos.evicted;
        for bar in &mut view.run.demos {
            if let Some(&id) = self.demos.episode_ids.get(bar.demo as usize) {
                bar.episode_id = id;
            }
        }
        if self.cfg.env.suite == Suite::Pointmaze {
            view.maze = Some(state.maze_view(&self.demos));
            for bar in &mut view.run.demos {
                bar.difficulty.cell = self.demos.maze_cell(bar.demo as usize, bar.t as usize);
            }
        }
        view
    }
}
