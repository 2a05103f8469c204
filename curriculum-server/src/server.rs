//! Runs the curriculum service: gRPC on one port, the dashboard on another, and the background
//! duties (lease expiry, progress samples, snapshots) until the shutdown signal; then a last
//! snapshot.
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use axum::extract::State;
use axum::http::header;
use axum::response::{Html, IntoResponse};
use axum::routing::get;
use rfcl_proto::auth::ServerAuth;
use rfcl_proto::health;
use rfcl_proto::v1::curriculum_server::CurriculumServer;
use tokio::net::TcpListener;
use tokio::sync::watch;
use tonic::server::NamedService;
use tonic::service::interceptor::InterceptedService;

use crate::service::{unix_now, CurriculumService, Shared};
use crate::{dashboard, snapshot};

/// The page refreshes itself this often.
pub const DASHBOARD_REFRESH_S: u32 = 2;
const HISTORY_EVERY: Duration = Duration::from_secs(2);
const SNAPSHOT_AT_LEAST_EVERY: Duration = Duration::from_secs(60);

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

/// The dashboard's routes: `/` (HTML), `/api/state` (JSON), `/metrics` (Prometheus text).
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
    axum::Router::new()
        .route("/", get(page))
        .route("/api/state", get(api_state))
        .route("/metrics", get(metrics))
        .with_state(shared)
}

/// Copies the state under the lock (cheap), then encodes and writes it outside the lock, so a
/// snapshot never stalls Acquire/Report for longer than a clone.
fn write_snapshot(shared: &Shared, run_dir: &std::path::Path) -> anyhow::Result<()> {
    let state = {
        let mut state = shared.lock();
        state.reports_since_snapshot = 0;
        state.clone()
    };
    let bytes = snapshot::encode(&state, &shared.cfg.name);
    snapshot::write(&snapshot::snapshot_path(run_dir), &bytes)?;
    Ok(())
}

/// Serves until `shutdown` resolves, then writes a last snapshot (when there is a run dir). Every
/// gRPC call must carry the run's token (`auth`, whose guard `shared` counts the refusals of); the
/// standard health service answers probes.
pub async fn serve(
    shared: Shared,
    bound: Bound,
    auth: ServerAuth,
    run_dir: Option<PathBuf>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let (stop_tx, stop_rx) = watch::channel(false);
    let stopped = |mut rx: watch::Receiver<bool>| async move {
        let _ = rx.wait_for(|s| *s).await;
    };

    // Lease expiry.
    let timeout = shared.cfg.service.lease_timeout_s;
    let s = shared.clone();
    let mut rx = stop_rx.clone();
    let expiry = tokio::spawn(async move {
        let mut tick =
            tokio::time::interval(Duration::from_secs_f64((timeout / 4.0).clamp(0.05, 1.0)));
        loop {
            tokio::select! { _ = tick.tick() => {}, _ = rx.changed() => break }
            let expired = s.lock().leases.expire(unix_now(), timeout);
            for g in expired {
                tracing::warn!(
                    lease = g.lease_id,
                    actor = g.actor_id,
                    "lease expired unreported after {timeout} s"
                );
            }
        }
    });
    // Progress samples for the dashboard.
    let s = shared.clone();
    let mut rx = stop_rx.clone();
    let history = tokio::spawn(async move {
        let mut tick = tokio::time::interval(HISTORY_EVERY);
        loop {
            tokio::select! { _ = tick.tick() => {}, _ = rx.changed() => break }
            s.lock().sample_history(unix_now());
        }
    });
    // Snapshots every N reports (and at least every minute while reports arrive).
    let snapshots = run_dir.clone().map(|dir| {
        let s = shared.clone();
        let mut rx = stop_rx.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(SNAPSHOT_AT_LEAST_EVERY);
            loop {
                tokio::select! {
                    _ = s.snapshot_due.notified() => {}
                    _ = tick.tick() => if s.lock().reports_since_snapshot == 0 { continue },
                    _ = rx.changed() => break,
                }
                let (s2, d2) = (s.clone(), dir.clone());
                match tokio::task::spawn_blocking(move || write_snapshot(&s2, &d2)).await {
                    Ok(Ok(())) => {}
                    Ok(Err(e)) => tracing::error!("snapshot failed: {e:#}"),
                    Err(e) => tracing::error!("snapshot task failed: {e}"),
                }
            }
        })
    });

    let dashboard = axum::serve(bound.dashboard, dashboard_router(shared.clone()))
        .with_graceful_shutdown(stopped(stop_rx.clone()));
    let (reporter, health) = health::health_reporter();
    health::serving(
        &reporter,
        <CurriculumServer<CurriculumService> as NamedService>::NAME,
    )
    .await;
    let curriculum = CurriculumServer::new(CurriculumService {
        shared: shared.clone(),
    });
    let grpc = rfcl_proto::link::server(auth.server().context("configuring TLS")?)
        .add_service(health)
        .add_service(InterceptedService::new(curriculum, auth.guard.clone()))
        .serve_with_incoming_shutdown(
            tokio_stream::wrappers::TcpListenerStream::new(bound.grpc),
            stopped(stop_rx.clone()),
        );
    let dashboard = tokio::spawn(async move { dashboard.await });
    let grpc = tokio::spawn(grpc);

    shutdown.await;
    tracing::info!("shutting down");
    let _ = stop_tx.send(true);
    let _ = tokio::join!(expiry, history);
    if let Some(t) = snapshots {
        let _ = t.await;
    }
    grpc.await.context("gRPC task")?.context("gRPC server")?;
    dashboard
        .await
        .context("dashboard task")?
        .context("dashboard server")?;
    if let Some(dir) = run_dir {
        write_snapshot(&shared, &dir).context("final snapshot")?;
        tracing::info!(
            "final snapshot written to {}",
            snapshot::snapshot_path(&dir).display()
        );
    }
    Ok(())
}
