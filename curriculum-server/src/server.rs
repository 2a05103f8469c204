//! Runs the curriculum service: gRPC on one port, the dashboard on another, and the background
//! duties (lease expiry and forgetting idle actors, progress samples, snapshots) until the
//! shutdown signal; then a last snapshot.
//!
//! Every one of these tasks runs for the life of the server, so one that ends early (an error, a
//! panic, or just returning) stops the whole server with an error naming it: a curriculum server
//! that no longer expires leases or snapshots must not look healthy. A stop waits at most
//! [`STOP_GRACE`] for calls in flight; WatchStage streams end on the stop by themselves.

use std::future::Future;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::Duration;

use anyhow::Context;
use axum::extract::State;
use axum::http::header;
use axum::response::{Html, IntoResponse};
use axum::routing::get;
use rfcl_core::video::MAX_EVAL_VIDEO_BYTES;
use rfcl_proto::auth::ServerAuth;
use rfcl_proto::health;
use rfcl_proto::v1::curriculum_server::CurriculumServer;
use rfcl_proto::v1::eval_videos_server::EvalVideosServer;
use tokio::net::TcpListener;
use tokio::time::Instant;
use tonic::server::NamedService;
use tonic::service::interceptor::InterceptedService;

use crate::dashboard_listener::{self, DashboardListener};
use crate::grpc::CurriculumService;
use crate::service::Shared;
use crate::state::unix_now;
use crate::videos::EvalVideosService;
use crate::{dashboard, snapshot};

/// The page refreshes itself this often.
pub const DASHBOARD_REFRESH_S: u32 = 2;
const HISTORY_EVERY: Duration = Duration::from_secs(2);
/// How long a stop waits for the servers to finish the calls in flight before dropping them, so
/// a client that never hangs up cannot hold the process (and its last snapshot) hostage.
pub const STOP_GRACE: Duration = Duration::from_secs(3);
/// Failed snapshot writes in a row after which the server stops with an error. A single failure
/// (a full disk for a moment) is logged, counted and retried; a run directory that stays
/// unwritable means a crash would lose the whole curriculum, so the run must not go on as if it
/// were protected.
pub const MAX_SNAPSHOT_FAILURES_IN_A_ROW: u32 = 5;
/// The largest request the curriculum service decodes. Its requests (Acquire, Report,
/// ReportAndAcquire, WatchStage, GetState) are a few dozen bytes; anything near this is not one
/// of ours and is refused before it is buffered.
pub const MAX_REQUEST_BYTES: usize = 64 << 10;
/// The largest reply it encodes: GetState's JSON view is the big one, bounded by the capped
/// history, the forgotten idle actors and the run's levels and evals; leases are a few KiB.
pub const MAX_REPLY_BYTES: usize = 16 << 20;

pub struct Bound {
    pub grpc: TcpListener,
    pub dashboard: TcpListener,
}

impl Bound {
    pub async fn bind(grpc: SocketAddr, dashboard: SocketAddr) -> anyhow::Result<Self> {
        Ok(Bound {
            grpc: TcpListener::bind(grpc)
                .await
                .with_context(|| format!("binding the gRPC port {grpc}"))?,
            dashboard: TcpListener::bind(dashboard)
                .await
                .with_context(|| format!("binding the dashboard port {dashboard}"))?,
        })
    }

    pub fn addrs(&self) -> std::io::Result<(SocketAddr, SocketAddr)> {
        Ok((self.grpc.local_addr()?, self.dashboard.local_addr()?))
    }
}

/// The dashboard's routes: `/` (HTML), `/api/state` (JSON), `/metrics` (Prometheus text),
/// `/videos/<name>` (the eval videos the view lists, GIF).
pub fn dashboard_router(shared: Shared) -> axum::Router {
    async fn page(State(s): State<Shared>) -> Html<String> {
        Html(dashboard::render_html(&s.view(), DASHBOARD_REFRESH_S))
    }
    async fn api_state(State(s): State<Shared>) -> axum::Json<dashboard::DashboardView> {
        axum::Json(s.view())
    }
    async fn metrics(State(s): State<Shared>) -> impl IntoResponse {
        let granted = s.lock().leases.granted_total();
        let text = dashboard::metrics_text(&s.view(), granted);
        (
            [(
                header::CONTENT_TYPE,
                "application/openmetrics-text; version=1.0.0; charset=utf-8",
            )],
            text,
        )
    }
    async fn video(
        State(s): State<Shared>,
        axum::extract::Path(name): axum::extract::Path<String>,
    ) -> axum::response::Response {
        let store = s.videos.clone();
        let lookup = name.clone();
        match tokio::task::spawn_blocking(move || store.read(&lookup)).await {
            Ok(Some(gif)) => ([(header::CONTENT_TYPE, "image/gif")], gif).into_response(),
            _ => (
                axum::http::StatusCode::NOT_FOUND,
                format!("no eval video named {name:?} in this run\n"),
            )
                .into_response(),
        }
    }
    axum::Router::new()
        .route("/", get(page))
        .route("/api/state", get(api_state))
        .route("/metrics", get(metrics))
        .route("/videos/{name}", get(video))
        .with_state(shared)
}

/// Copies the state under the lock (cheap), then encodes and writes it outside the lock, so a
/// snapshot never stalls Acquire/Report for longer than a clone. The reports it covers stop
/// counting towards the next snapshot only once it is written, so a failed write is retried.
fn write_snapshot(shared: &Shared, run_dir: &Path) -> anyhow::Result<()> {
    let (state, covered) = {
        let state = shared.lock();
        let covered = state.reports_since_snapshot;
        (state.clone(), covered)
    };
    let bytes = snapshot::encode(&state, &shared.cfg.name);
    snapshot::save(run_dir, &bytes)?;
    let mut state = shared.lock();
    state.reports_since_snapshot = state.reports_since_snapshot.saturating_sub(covered);
    Ok(())
}

/// Resolves once the server stops.
fn stopped(shared: &Shared) -> impl Future<Output = ()> + Send + 'static {
    let mut rx = shared.stopping.subscribe();
    async move {
        let _ = rx.wait_for(|s| *s).await;
    }
}

/// Expires unreported leases and forgets actors that stopped calling.
async fn expiry_loop(s: Shared) -> anyhow::Result<()> {
    let timeout = s.cfg.service.lease_timeout_s;
    let forget_after = s.cfg.service.forget_actors_after_s;
    let mut tick = tokio::time::interval(Duration::from_secs_f64((timeout / 4.0).clamp(0.05, 1.0)));
    let stop = stopped(&s);
    tokio::pin!(stop);
    loop {
        tokio::select! { _ = tick.tick() => {}, _ = &mut stop => return Ok(()) }
        let now = unix_now();
        let (expired, forgotten) = {
            let mut state = s.lock();
            let expired = state.leases.expire(now, timeout);
            (expired, state.forget_idle_actors(now, forget_after))
        };
        for g in expired {
            tracing::warn!(
                lease = g.lease_id,
                actor = g.actor_id,
                "lease expired unreported after {timeout} s"
            );
        }
        if forgotten > 0 {
            tracing::info!(
                forgotten,
                "forgot actors silent for over service.forget_actors_after_s = {forget_after} s"
            );
        }
    }
}

/// Progress samples for the dashboard.
async fn history_loop(s: Shared) -> anyhow::Result<()> {
    let mut tick = tokio::time::interval(HISTORY_EVERY);
    let stop = stopped(&s);
    tokio::pin!(stop);
    loop {
        tokio::select! { _ = tick.tick() => {}, _ = &mut stop => return Ok(()) }
        s.lock().sample_history(unix_now());
    }
}

/// Snapshots every `service.snapshot_every_reports` reports, and `service.snapshot_every_s` after
/// the last one when reports arrived since. A failed write is logged, counted and retried on the
/// timer; [`MAX_SNAPSHOT_FAILURES_IN_A_ROW`] failures end the task with the last error.
async fn snapshot_loop(s: Shared, dir: PathBuf) -> anyhow::Result<()> {
    let every = Duration::from_secs_f64(s.cfg.service.snapshot_every_s);
    let mut last = Instant::now();
    let mut failures_in_a_row = 0u32;
    let stop = stopped(&s);
    tokio::pin!(stop);
    loop {
        tokio::select! {
            // After a failure, retry on the timer only: a report burst must not hammer a bad disk.
            _ = s.snapshot_due.notified(), if failures_in_a_row == 0 => {}
            _ = tokio::time::sleep_until(last + every) => {
                if s.lock().reports_since_snapshot == 0 {
                    last = Instant::now();
                    continue;
                }
            }
            _ = &mut stop => return Ok(()),
        }
        last = Instant::now();
        let (s2, d2) = (s.clone(), dir.clone());
        let result = tokio::task::spawn_blocking(move || write_snapshot(&s2, &d2))
            .await
            .context("the snapshot write panicked")
            .and_then(|r| r);
        match result {
            Ok(()) => failures_in_a_row = 0,
            Err(e) => {
                failures_in_a_row += 1;
                s.snapshot_failures.fetch_add(1, Ordering::Relaxed);
                if failures_in_a_row >= MAX_SNAPSHOT_FAILURES_IN_A_ROW {
                    return Err(e.context(format!(
                        "{failures_in_a_row} snapshot writes in a row failed"
                    )));
                }
                tracing::error!(
                    failures_in_a_row,
                    "snapshot failed (retried in {} s; the server stops after {} in a row): {e:#}",
                    every.as_secs_f64(),
                    MAX_SNAPSHOT_FAILURES_IN_A_ROW
                );
            }
        }
    }
}

/// Whether a gRPC response is tonic's refusal of a request over [`MAX_REQUEST_BYTES`]: tonic
/// refuses it while decoding, before any handler runs, as a trailers-only response with
/// OUT_OF_RANGE and a (percent-encoded) message saying the message is too large. Counting it here
/// is the only place such a call is seen.
fn is_oversized_refusal(headers: &axum::http::HeaderMap) -> bool {
    let status = headers.get("grpc-status").map(|v| v.as_bytes());
    let message = headers
        .get("grpc-message")
        .and_then(|v| v.to_str().ok())
        .unwrap_or_default();
    status == Some(b"11") && message.contains("too%20large")
}

/// Serves until `shutdown` resolves (or one of the server's own tasks ends, which is an error
/// naming it), then writes a last snapshot (when there is a run dir). Every gRPC call must carry
/// the run's token (`auth`, whose guard `shared` counts the refusals of); the standard health
/// service answers probes.
pub async fn serve(
    shared: Shared,
    bound: Bound,
    auth: ServerAuth,
    run_dir: Option<PathBuf>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let mut tasks = rfcl_runtime::tasks::Tasks::default();
    tasks.spawn("lease-expiry loop", expiry_loop(shared.clone()));
    tasks.spawn("history sampler", history_loop(shared.clone()));
    let learner = shared.learner.clone();
    let stop = stopped(&shared);
    tasks.spawn("learner poll", async move { learner.poll_loop(stop).await });
    if let Some(dir) = run_dir.clone() {
        tasks.spawn("snapshot writer", snapshot_loop(shared.clone(), dir));
    }

    let listener = DashboardListener::new(
        bound.dashboard,
        dashboard_listener::MAX_CONNECTIONS,
        dashboard_listener::IDLE_TIMEOUT,
        shared.dashboard_refused.clone(),
    );
    let dashboard = axum::serve(listener, dashboard_router(shared.clone()))
        .with_graceful_shutdown(stopped(&shared));
    tasks.spawn("dashboard server", async move {
        dashboard.await.context("dashboard server")
    });
    let (reporter, health) = health::health_reporter();
    health::serving(
        &reporter,
        <CurriculumServer<CurriculumService> as NamedService>::NAME,
    )
    .await;
    let curriculum = CurriculumServer::new(CurriculumService {
        shared: shared.clone(),
    })
    .max_decoding_message_size(MAX_REQUEST_BYTES)
    .max_encoding_message_size(MAX_REPLY_BYTES);
    let videos = EvalVideosServer::new(EvalVideosService {
        store: shared.videos.clone(),
    })
    .max_decoding_message_size(MAX_EVAL_VIDEO_BYTES + MAX_REQUEST_BYTES);
    let oversized = shared.oversized_requests.clone();
    let grpc = rfcl_proto::link::server(auth.server().context("configuring TLS")?)
        .layer(tower::util::MapResponseLayer::new(
            move |response: axum::http::Response<tonic::body::Body>| {
                if is_oversized_refusal(response.headers()) {
                    oversized.fetch_add(1, Ordering::Relaxed);
                }
                response
            },
        ))
        .add_service(health)
        .add_service(InterceptedService::new(curriculum, auth.guard.clone()))
        .add_service(InterceptedService::new(videos, auth.guard.clone()))
        .serve_with_incoming_shutdown(
            tokio_stream::wrappers::TcpListenerStream::new(bound.grpc),
            stopped(&shared),
        );
    tasks.spawn(
        "gRPC server",
        async move { grpc.await.context("gRPC server") },
    );

    let failed = tokio::select! {
        _ = shutdown => None,
        e = tasks.first_end() => Some(e),
    };
    match &failed {
        None => tracing::info!("shutting down"),
        Some(e) => tracing::error!("{e:#}; shutting down"),
    }
    shared.stopping.send_replace(true);
    let finished = tasks.finish(STOP_GRACE).await;
    if let Some(dir) = run_dir {
        match write_snapshot(&shared, &dir) {
            Ok(()) => tracing::info!(
                "final snapshot written to {}",
                snapshot::snapshot_path(&dir).display()
            ),
            // The task's failure is the error to return; the snapshot's is logged with it.
            Err(e) if failed.is_some() => tracing::error!("final snapshot: {e:#}"),
            Err(e) => return Err(e.context("final snapshot")),
        }
    }
    match failed {
        Some(e) => Err(e),
        None => finished.map(|_| ()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::state::{DemoResets, ServerState};
    use crate::{Curriculum, DemoMeta};
    use rfcl_core::config::RunConfig;
    use rfcl_core::lease::{AcquireRequest, EpisodeReport, ResetArgs};
    use rfcl_proto::auth::{Guard, Token};

    fn token() -> Token {
        Token::parse("server-unit-test-token-0123", "a test").unwrap()
    }

    fn shared(cfg: RunConfig) -> Shared {
        let metas = [DemoMeta {
            success: vec![false, false, true],
            reset_seed: Some(0),
        }];
        let state = ServerState::new(Curriculum::new(&cfg, &metas).unwrap(), unix_now());
        let demos = DemoResets {
            state_dim: 1,
            states: vec![vec![0.0, 1.0, 2.0, 3.0]],
            reset: vec![ResetArgs::default()],
            episode_ids: vec![0],
        };
        Shared::new(state, cfg, demos, Guard::new(&token()))
    }

    async fn bound() -> Bound {
        let any: SocketAddr = "127.0.0.1:0".parse().unwrap();
        Bound::bind(any, any).await.unwrap()
    }

    /// Applies one train report in-process, as the gRPC service does.
    fn one_report(shared: &Shared) {
        let mut state = shared.lock();
        let req = AcquireRequest {
            actor_id: 1,
            env_index: 0,
            eval: false,
        };
        let lease = state
            .acquire(req, &shared.cfg, &shared.demos, unix_now())
            .unwrap();
        let report = EpisodeReport {
            lease_id: lease.lease_id,
            success_at_end: false,
            success_once: false,
            episode_return: 0.0,
            length: 1,
            policy_version: 0,
            stage_epoch: lease.stage_epoch,
            actor_id: 1,
            actor_env_steps: 1,
            policy_env_steps: 0,
            sim_restarts: 0,
            reset_failure: None,
        };
        state.report(&report, &shared.cfg, unix_now()).unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_snapshot_follows_wall_time_once_reports_arrived() {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = RunConfig {
            name: "walltime".into(),
            ..RunConfig::default()
        };
        cfg.service.snapshot_every_s = 0.3;
        cfg.service.snapshot_every_reports = 1_000_000;
        let shared = shared(cfg);
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(serve(
            shared.clone(),
            bound().await,
            rfcl_proto::auth::ServerAuth::plain(&token()),
            Some(dir.path().to_path_buf()),
            async move {
                let _ = stop_rx.await;
            },
        ));
        let path = snapshot::snapshot_path(dir.path());
        // No reports, no snapshot, however much time passes.
        tokio::time::sleep(Duration::from_millis(900)).await;
        assert!(!path.exists(), "a snapshot without reports");
        one_report(&shared);
        let t0 = std::time::Instant::now();
        while !path.exists() && t0.elapsed() < Duration::from_secs(5) {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(path.exists(), "no snapshot 5 s after a report");
        assert!(
            t0.elapsed() < Duration::from_millis(1500),
            "{:?}",
            t0.elapsed()
        );
        let snap = snapshot::load(&path, "walltime").unwrap();
        assert_eq!(snap.stats.episodes, 1);
        assert_eq!(shared.lock().reports_since_snapshot, 0);
        stop_tx.send(()).unwrap();
        server.await.unwrap().unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_run_dir_that_stays_unwritable_stops_the_server_with_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let run_dir = dir.path().join("run");
        // A file where the run directory should be: no snapshot can be written there, even as root.
        std::fs::write(&run_dir, b"not a directory").unwrap();
        let mut cfg = RunConfig::default();
        cfg.service.snapshot_every_s = 0.05;
        let shared = shared(cfg);
        one_report(&shared);
        let served = tokio::time::timeout(
            Duration::from_secs(20),
            serve(
                shared.clone(),
                bound().await,
                rfcl_proto::auth::ServerAuth::plain(&token()),
                Some(run_dir),
                std::future::pending(),
            ),
        )
        .await
        .expect("serve went on with snapshots failing");
        let err = format!("{:#}", served.unwrap_err());
        assert!(
            err.contains("the snapshot writer task failed")
                && err.contains(&format!(
                    "{MAX_SNAPSHOT_FAILURES_IN_A_ROW} snapshot writes in a row failed"
                )),
            "{err}"
        );
        assert_eq!(
            shared.view().snapshot_failures,
            u64::from(MAX_SNAPSHOT_FAILURES_IN_A_ROW)
        );
        // The reports the failed snapshots should have covered are still waiting for one.
        assert_eq!(shared.lock().reports_since_snapshot, 1);
    }
}
