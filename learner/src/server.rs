//! The learner service as a library, in two steps like every rfcl service: [`Server::start`]
//! does what can fail before the ready line (the shared-memory transport, the gRPC service, the
//! metrics endpoint), and [`Server::serve`] runs until the stop: the training thread, the gRPC
//! server, the metrics server and the stage subscription, each a named task under one supervisor
//! ([`rfcl_runtime::tasks::Tasks`]). A task that ends or fails before the stop stops the learner
//! after its final checkpoint, with an error naming it. The `learner` binary loads the config,
//! the demos and the checkpoint, builds the [`Trainer`], binds, prints [`Server::ready_line`] and
//! calls them.
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use rfcl_core::config::RunConfig;
use rfcl_core::final_counters::{FinalCounters, LearnerCounts, FINAL_COUNTERS_FILE};
use rfcl_core::ready::ReadyLine;
use rfcl_proto::auth::{ClientAuth, ServerAuth};
use rfcl_proto::v1;
use tokio::net::TcpListener;
use tokio::sync::{mpsc, oneshot, watch};
use tonic::Streaming;

use crate::ingest::IngestCounters;
use crate::service::{self, LearnerService, RunDescription};
use crate::shm::ShmTransport;
use crate::stages::{self, StageAnnouncement};
use crate::trainer::{LearnerStatus, PolicyWatch, StopReason, Trainer, TrainerInputs};

/// How long the stop waits for the learner's own tasks, and for the shared-memory threads.
const TASKS_GRACE: Duration = Duration::from_secs(5);

/// The learner's ports, bound before anything is served.
pub struct Bound {
    pub grpc: TcpListener,
    pub metrics: Option<TcpListener>,
}

impl Bound {
    /// Binds gRPC on `ip:port` and, when asked, Prometheus `/metrics` on `ip:metrics_port` (port
    /// 0: a free one).
    pub async fn bind(ip: IpAddr, port: u16, metrics_port: Option<u16>) -> Result<Self> {
        let grpc = TcpListener::bind(SocketAddr::new(ip, port))
            .await
            .with_context(|| format!("binding the gRPC port {ip}:{port}"))?;
        let metrics = match metrics_port {
            Some(port) => Some(
                TcpListener::bind(SocketAddr::new(ip, port))
                    .await
                    .with_context(|| format!("binding the metrics port {ip}:{port}"))?,
            ),
            None => None,
        };
        Ok(Self { grpc, metrics })
    }
}

/// What the learner serves: the trainer built from the config, the demos and (when resuming) its
/// checkpoint, with the first stage subscription it was built under.
pub struct Inputs {
    pub cfg: RunConfig,
    pub run_dir: PathBuf,
    pub trainer: Trainer,
    pub policy: PolicyWatch,
    pub status: Arc<LearnerStatus>,
    /// The curriculum server's address, its first stage announcement and the subscription that
    /// brought it.
    pub curriculum: String,
    pub first_stage: StageAnnouncement,
    pub stage_stream: Streaming<v1::StageEvent>,
    /// How long calls to the curriculum server may take to connect.
    pub connect_timeout: Duration,
    /// The URL at which the curriculum server reaches this learner (its dashboard's learner
    /// panel); `None`: the bound address, or this host's name when bound to every interface.
    pub advertise: Option<String>,
    /// Capacity of the ingest queue, in transition batches.
    pub queue_batches: usize,
    /// Serve the shared-memory transport beside gRPC.
    pub shm: bool,
    pub server_auth: ServerAuth,
    pub client_auth: ClientAuth,
}

/// A learner that is set up and bound, not yet serving.
pub struct Server {
    inputs: Inputs,
    grpc_addr: SocketAddr,
    metrics_url: Option<String>,
    service: LearnerService,
    grpc: TcpListener,
    shm: Option<ShmTransport>,
    counters: Arc<IngestCounters>,
    data: mpsc::Receiver<crate::ingest::IngestItem>,
    stopping: watch::Sender<bool>,
    tasks: rfcl_runtime::tasks::Tasks,
}

impl Server {
    /// Starts the shared-memory transport (unless `inputs.shm` is false) and the metrics server,
    /// and builds the gRPC service; nothing trains yet.
    pub fn start(bound: Bound, inputs: Inputs) -> Result<Self> {
        let grpc_addr = bound
            .grpc
            .local_addr()
            .context("reading the bound address")?;
        let trainer = &inputs.trainer;
        let layout = trainer.layout();
        let info = RunDescription {
            run_name: inputs.cfg.name.clone(),
            env_id: trainer.env_id().to_string(),
            obs_dim: layout.obs_dim as u32,
            action_dim: layout.action_dim as u32,
            curriculum_addr: inputs.curriculum.clone(),
            config_yaml: trainer.config_yaml().to_string(),
            run_seed: inputs.cfg.seed,
            learner_hostname: hostname(),
            run_id: rfcl_shm::new_run_id(),
            host_identity: rfcl_shm::host_identity(),
            shm: None,
            action_scale: trainer.action_scale().map(<[f32]>::to_vec),
        };
        let counters = IngestCounters::new();
        let (data_tx, data_rx) = mpsc::channel(inputs.queue_batches.max(1));
        let (stopping_tx, stopping_rx) = watch::channel(false);
        // Same-host actors: transitions in and policies out over iceoryx2 (learner/src/shm.rs).
        let shm = inputs
            .shm
            .then(|| {
                ShmTransport::start_for(
                    &info,
                    layout,
                    &inputs.status,
                    &data_tx,
                    &inputs.policy,
                    &counters,
                    &stopping_rx,
                )
            })
            .transpose()
            .context("starting the shared-memory transport (--no-shm serves gRPC only)")?;
        let info = RunDescription {
            shm: shm.as_ref().map(|s| s.names.clone()),
            ..info
        };
        let service = LearnerService::new(
            info,
            inputs.status.clone(),
            data_tx,
            inputs.policy.clone(),
            stopping_rx.clone(),
            counters.clone(),
            inputs.server_auth.guard.clone(),
        )
        .with_transition_batch(inputs.cfg.service.transition_batch);

        // Every task here serves until the stop: one that ends or fails earlier stops the
        // learner (after its final checkpoint) with an error naming it.
        let mut tasks = rfcl_runtime::tasks::Tasks::default();
        let metrics_url = match bound.metrics {
            Some(listener) => {
                let at = listener
                    .local_addr()
                    .context("reading the bound metrics address")?;
                let metrics = inputs.trainer.metrics();
                metrics.add_collector(counters.clone());
                metrics.add_collector(Arc::new(crate::prom::Unauthenticated(
                    inputs.server_auth.guard.clone(),
                )));
                let serve = crate::prom::serve(listener, metrics, stopped(&stopping_rx));
                tasks.spawn("metrics server", async move {
                    serve.await.context("serving /metrics")
                });
                let url = crate::prom::describe(at);
                tracing::info!("Prometheus metrics at {url}");
                Some(url)
            }
            None => None,
        };
        Ok(Self {
            inputs,
            grpc_addr,
            metrics_url,
            service,
            grpc: bound.grpc,
            shm,
            counters,
            data: data_rx,
            stopping: stopping_tx,
            tasks,
        })
    }

    /// `learner ready grpc=ADDR [metrics=URL]`: the one machine-readable line on stdout, from
    /// which `rfcl train` and the tests read the addresses.
    pub fn ready_line(&self) -> ReadyLine {
        let grpc = self.grpc_addr.to_string();
        let mut fields = vec![("grpc", grpc.as_str())];
        fields.extend(self.metrics_url.as_deref().map(|url| ("metrics", url)));
        ReadyLine::new("learner", &fields)
    }

    /// Trains and serves until the budget, the curriculum's end or a stop request: the first
    /// message on `stops` finishes with a final checkpoint, a second aborts before it. Writes the
    /// learner's final counters ([`FINAL_COUNTERS_FILE`]) after a clean finish.
    pub async fn serve(self, mut stops: mpsc::UnboundedReceiver<()>) -> Result<()> {
        let Server {
            inputs,
            grpc_addr,
            service,
            grpc,
            shm,
            counters,
            data,
            stopping,
            mut tasks,
            ..
        } = self;
        let stopping_rx = stopping.subscribe();
        let (stage_tx, stage_rx) = mpsc::unbounded_channel();
        // The first subscription was made before this learner could serve; subscribe again with
        // its address so that the curriculum server's dashboard polls its Health. The new
        // stream's first announcement goes to the trainer too, in case the stage moved in between.
        let advertise = inputs
            .advertise
            .clone()
            .unwrap_or_else(|| advertised_url(grpc_addr, inputs.server_auth.tls()));
        rfcl_proto::convert::learner_addr(&v1::WatchStageRequest {
            learner_addr: advertise.clone(),
        })
        .context("--advertise (RFCL_LEARNER_ADVERTISE)")?;
        let stage_stream = match stages::open(
            &inputs.curriculum,
            &inputs.client_auth,
            inputs.connect_timeout,
            &advertise,
        )
        .await
        {
            Ok((announced, current)) => {
                drop(inputs.stage_stream);
                let _ = stage_tx.send(current);
                tracing::info!("announced to the curriculum server at {advertise}");
                announced
            }
            // Training does not need the panel: go on with the first subscription, which
            // announces this learner once it is re-opened.
            Err(e) => {
                tracing::warn!(
                    "could not announce this learner at {advertise} to the curriculum server ({}); its dashboard shows no learner panel until the stage subscription is re-opened",
                    crate::error::chain(&e)
                );
                inputs.stage_stream
            }
        };
        let follow = stages::follow(
            inputs.curriculum.clone(),
            inputs.client_auth,
            advertise,
            stage_stream,
            stage_tx,
            stopping_rx.clone(),
        );
        let mut stopped_follow = stopping_rx.clone();
        tasks.spawn("stage subscription", async move {
            follow.await;
            // It also ends when the training thread, its receiver, is done: wait for the stop.
            let _ = stopped_follow.wait_for(|s| *s).await;
            Ok(())
        });
        let (shutdown_tx, shutdown_rx) = watch::channel(false);
        let trainer_inputs = TrainerInputs {
            data,
            stages: stage_rx,
            shutdown: shutdown_rx,
            runtime: tokio::runtime::Handle::current(),
        };
        let (done_tx, mut done_rx) = oneshot::channel();
        let (trainer, first_stage) = (inputs.trainer, inputs.first_stage);
        std::thread::Builder::new()
            .name("trainer".into())
            .spawn(move || {
                let _ = done_tx.send(trainer.run(trainer_inputs, first_stage));
            })
            .context("starting the training thread")?;
        let serve = service::serve(grpc, service, inputs.server_auth, stopped(&stopping_rx));
        tasks.spawn(
            "gRPC server",
            async move { serve.await.context("gRPC server") },
        );

        let mut failed = None;
        let outcome = tokio::select! {
            done = &mut done_rx => done,
            e = tasks.first_end() => {
                tracing::error!("{e:#}: finishing (final checkpoint)");
                failed = Some(e);
                let _ = shutdown_tx.send(true);
                (&mut done_rx).await
            }
            _ = next_stop(&mut stops) => {
                tracing::info!("signal received: finishing (final checkpoint); signal again to abort");
                let _ = shutdown_tx.send(true);
                tokio::select! {
                    done = &mut done_rx => done,
                    _ = next_stop(&mut stops) => bail!("aborted by a second signal before the final checkpoint"),
                }
            }
        };
        let _ = stopping.send(true);
        if let Some(shm) = shm {
            let _ = tokio::task::spawn_blocking(move || shm.join(TASKS_GRACE)).await;
        }
        let totals = counters.totals();
        tracing::info!("transitions taken in: {totals}");
        if matches!(outcome, Ok(Ok(_))) {
            let s = inputs.status.snapshot();
            let last = FinalCounters {
                pid: std::process::id(),
                counts: LearnerCounts {
                    env_steps: s.env_steps,
                    updates: s.critic_updates,
                    policy_version: s.policy_version,
                    shm_records: totals.shm_records,
                    grpc_records: totals.grpc_records,
                    shm_lost_records: totals.shm_lost_records,
                    refused_batches: totals.refused_batches,
                    dropped_stale_epoch: s.dropped_stale_epoch,
                    unused_records: totals.unused_records,
                },
            };
            let path = inputs.run_dir.join(FINAL_COUNTERS_FILE);
            let json = serde_json::to_vec_pretty(&last).expect("counters serialize");
            if let Err(e) = rfcl_core::atomic::atomic_write(&path, &json) {
                tracing::warn!("writing {}: {e}", path.display());
            }
        }
        if let Err(e) = tasks.finish(TASKS_GRACE).await {
            tracing::warn!("stopping: {e:#}");
        }
        if let Some(e) = failed {
            return Err(e);
        }
        match outcome {
            Ok(Ok(reason)) => {
                let why = match reason {
                    StopReason::Budget => "train.steps reached",
                    StopReason::Signal => "stopped by a signal",
                    StopReason::CurriculumFinished => "the curriculum server ended the run",
                    StopReason::InputsClosed => "the ingest queue closed",
                };
                tracing::info!("learner done: {why}");
                Ok(())
            }
            Ok(Err(e)) => Err(e).context("training"),
            Err(_) => bail!("the training thread panicked"),
        }
    }
}

/// The next stop request; a closed channel asks for none.
async fn next_stop(stops: &mut mpsc::UnboundedReceiver<()>) {
    if stops.recv().await.is_none() {
        std::future::pending::<()>().await;
    }
}

/// Resolves once `stopping` turns true.
fn stopped(stopping: &watch::Receiver<bool>) -> impl std::future::Future<Output = ()> + 'static {
    let mut stopping = stopping.clone();
    async move {
        let _ = stopping.wait_for(|s| *s).await;
    }
}

/// The URL of this learner's gRPC as another host names it: the bound address, or this host's
/// name when bound to every interface.
fn advertised_url(bound: SocketAddr, tls: bool) -> String {
    let scheme = if tls { "https" } else { "http" };
    let host = match bound.ip() {
        ip if ip.is_unspecified() => hostname(),
        IpAddr::V6(ip) => format!("[{ip}]"),
        IpAddr::V4(ip) => ip.to_string(),
    };
    format!("{scheme}://{host}:{}", bound.port())
}

/// This host's name (the kernel's, else `$HOSTNAME`, else `localhost`).
fn hostname() -> String {
    std::fs::read_to_string(Path::new("/proc/sys/kernel/hostname"))
        .map(|s| s.trim().to_string())
        .ok()
        .filter(|s| !s.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "localhost".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_advertised_url_is_the_bound_address_or_the_host_name() {
        let at = |ip: &str| SocketAddr::new(ip.parse().unwrap(), 50052);
        assert_eq!(
            advertised_url(at("127.0.0.1"), false),
            "http://127.0.0.1:50052"
        );
        assert_eq!(advertised_url(at("::1"), true), "https://[::1]:50052");
        assert_eq!(
            advertised_url(at("0.0.0.0"), false),
            format!("http://{}:50052", hostname())
        );
    }
}
