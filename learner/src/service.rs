//! The `rfcl.v1.Learner` gRPC service: a thin shell over the training thread.
//!
//! * `GetRunInfo`: the run description actors start from (dims, env id, curriculum address,
//!   resolved config as YAML, run seed, the learner's host, spec 6.4's action scale when the run
//!   sets `train.data_action_scale`), and the transport: the shared-memory
//!   service names of this learner session with its host identity, and `transport` = "shm" for
//!   an actor whose host identity equals the learner's (the actor still decides: `--transport`).
//! * `PushTransitions`: client stream of validated [`TransitionBatch`](v1::TransitionBatch)es into
//!   the bounded ingest queue. When the training thread falls behind (the `sync` UTD limiter), the
//!   queue fills, this handler stops reading its stream and HTTP/2 flow control holds the actor
//!   back. The answer, once the stream closed and every batch of it was handled, gives exact
//!   counts: records stored and records dropped because their stage epoch had ended. HTTP/2's
//!   receive windows are small ([`STREAM_WINDOW_BYTES`]), so bytes in flight on a stream stay
//!   within a few batches.
//! * `WatchPolicy`: the current version first when newer than `after_version`, then each newer one
//!   as it is published. Versions are immutable `Arc`s in a `watch` channel: a reader never sees a
//!   torn version, and a slow reader skips straight to the latest. The weights are `bytes::Bytes`:
//!   every subscriber's message shares the one buffer (no copy per subscriber). The stream ends
//!   when training ends.
//! * `Health`: critic updates (`updates`), env steps received and stored, policy version, read
//!   together at one consistent point of the training loop; `ok` is false once training failed;
//!   and the records and batches taken in per transport ([`IngestCounters`]).
//!
//! Message limits: tonic sets its decoding limit per service, not per RPC, and every RPC of this
//! service but `PushTransitions` carries a few hundred bytes. The limit is therefore the largest
//! `TransitionBatch` an actor sends ([`max_request_bytes`]: `service.transition_batch` records
//! with a 2× margin, plus 64 KiB for the rest), not the 256 MB that let each concurrent caller make
//! the learner buffer a huge request. A larger request is refused before it is buffered whole: a
//! `TransitionBatch` with `RESOURCE_EXHAUSTED`, counted as a refused batch; a unary request with
//! tonic's own `OUT_OF_RANGE` (it is decoded before any handler runs).
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use rfcl_core::transition::RecordLayout;
use rfcl_proto::auth::{Guard, ServerAuth};
use rfcl_proto::health;
use rfcl_proto::v1;
use rfcl_proto::v1::learner_server::{Learner, LearnerServer};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tokio_stream::{Stream, StreamExt};
use tonic::server::NamedService;
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status, Streaming};

use crate::ingest::{validate_batch, IngestCounters, IngestItem, StreamTally, Transport};
use crate::trainer::{LearnerStatus, PolicyWatch, WindowStats};

/// Largest gRPC message sent (policy weights of wide networks). What the learner accepts is
/// [`max_request_bytes`].
pub const MAX_MESSAGE_BYTES: usize = 256 << 20;

/// Room for the requests other than `PushTransitions` (run info, policy watch, health: all a few
/// hundred bytes) and for a `TransitionBatch`'s own fields.
pub const SMALL_REQUEST_BYTES: usize = 64 << 10;

/// The decoding limit of the learner service: a `TransitionBatch` of twice `transition_batch`
/// records of `layout` (actors send at most `transition_batch`; the margin keeps a learner and
/// actors whose configs differ a little working) plus [`SMALL_REQUEST_BYTES`].
pub fn max_request_bytes(layout: RecordLayout, transition_batch: u32) -> usize {
    2 * transition_batch.max(1) as usize * layout.record_bytes() + SMALL_REQUEST_BYTES
}

/// HTTP/2 receive window per stream (the protocol's default, 64 KiB, instead of hyper's 1 MiB):
/// what a remote actor may have in flight on its PushTransitions stream beyond what the learner
/// has read. About 2 batches of 64 paper-size records (400 B each); smaller records fit more.
pub const STREAM_WINDOW_BYTES: u32 = 64 << 10;
/// HTTP/2 receive window per connection: a few streams' worth.
pub const CONNECTION_WINDOW_BYTES: u32 = 256 << 10;

/// The run description `GetRunInfo` answers with (its dynamic part, the policy version, comes
/// from the training thread).
#[derive(Debug, Clone, PartialEq)]
pub struct RunDescription {
    pub run_name: String,
    pub env_id: String,
    pub obs_dim: u32,
    pub action_dim: u32,
    pub curriculum_addr: String,
    pub config_yaml: String,
    pub run_seed: u64,
    pub learner_hostname: String,
    /// This learner session's id (part of the shared-memory service names).
    pub run_id: String,
    /// [`rfcl_shm::host_identity`] of the learner's host.
    pub host_identity: String,
    /// The shared-memory services, when this learner serves them (`None`: gRPC only).
    pub shm: Option<rfcl_shm::ServiceNames>,
    /// Spec 6.4's per-dimension action scale s (`train.data_action_scale`), `action_dim` values;
    /// `None` = no scaling. Actors step their envs with a / s.
    pub action_scale: Option<Vec<f32>>,
}

impl RunDescription {
    /// The transport this learner recommends to an actor with host identity `actor_host`:
    /// shared memory when it serves it and the actor shares its host (and `/dev/shm`).
    pub fn transport_for(&self, actor_host: &str) -> &'static str {
        if self.shm.is_some() && !actor_host.is_empty() && actor_host == self.host_identity {
            "shm"
        } else {
            "grpc"
        }
    }
}

#[derive(Clone)]
pub struct LearnerService {
    info: Arc<RunDescription>,
    layout: RecordLayout,
    status: Arc<LearnerStatus>,
    ingest: mpsc::Sender<IngestItem>,
    policy: PolicyWatch,
    /// True once the learner is shutting down: open streams are answered and closed.
    stopping: watch::Receiver<bool>,
    counters: Arc<IngestCounters>,
    /// The token check of this service: Health reports its refusals.
    guard: Guard,
    /// `service.transition_batch`: sizes the decoding limit ([`max_request_bytes`]).
    transition_batch: u32,
}

impl LearnerService {
    pub fn new(
        info: RunDescription,
        status: Arc<LearnerStatus>,
        ingest: mpsc::Sender<IngestItem>,
        policy: PolicyWatch,
        stopping: watch::Receiver<bool>,
        counters: Arc<IngestCounters>,
        guard: Guard,
    ) -> Self {
        let layout = RecordLayout::new(info.obs_dim as usize, info.action_dim as usize);
        Self {
            info: Arc::new(info),
            layout,
            status,
            ingest,
            policy,
            stopping,
            counters,
            guard,
            transition_batch: rfcl_core::config::ServiceConfig::default().transition_batch,
        }
    }

    /// Sizes the decoding limit for batches of `rows` records (`service.transition_batch`).
    pub fn with_transition_batch(mut self, rows: u32) -> Self {
        self.transition_batch = rows;
        self
    }

    /// The largest request this service decodes ([`max_request_bytes`]).
    pub fn max_request_bytes(&self) -> usize {
        max_request_bytes(self.layout, self.transition_batch)
    }

    /// The tonic service with this crate's message limits (module docs).
    pub fn into_server(self) -> LearnerServer<Self> {
        let limit = self.max_request_bytes();
        LearnerServer::new(self)
            .max_decoding_message_size(limit)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
    }
}

impl LearnerService {
    /// tonic answers a message over the decoding limit OUT_OF_RANGE; gRPC's code for it is
    /// RESOURCE_EXHAUSTED, which is what an actor gets for an oversized batch (counted as a
    /// refused batch). Other errors pass unchanged.
    fn refuse_oversized(&self, status: Status) -> Status {
        let oversized = matches!(
            status.code(),
            tonic::Code::OutOfRange | tonic::Code::ResourceExhausted
        ) && status.message().contains("too large");
        if !oversized {
            return status;
        }
        self.counters
            .grpc
            .refused_batches
            .fetch_add(1, Ordering::Relaxed);
        let limit = self.max_request_bytes();
        tracing::warn!(
            "refused a TransitionBatch over the {limit} B limit (service.transition_batch = {} records): {}",
            self.transition_batch,
            status.message()
        );
        Status::resource_exhausted(format!(
            "TransitionBatch: {}; the learner takes batches up to {limit} B (service.transition_batch = {} records of {} B, with a 2x margin)",
            status.message(),
            self.transition_batch,
            self.layout.record_bytes()
        ))
    }
}

fn shutting_down() -> Status {
    Status::unavailable("the learner is shutting down")
}

type PolicyStream = Pin<Box<dyn Stream<Item = Result<v1::PolicyWeights, Status>> + Send>>;

#[tonic::async_trait]
impl Learner for LearnerService {
    async fn get_run_info(
        &self,
        request: Request<v1::GetRunInfoRequest>,
    ) -> Result<Response<v1::RunInfo>, Status> {
        let info = &self.info;
        let (transitions, policy) = info.shm.as_ref().map_or_else(Default::default, |n| {
            (n.transitions.clone(), n.policy.clone())
        });
        Ok(Response::new(v1::RunInfo {
            run_name: info.run_name.clone(),
            env_id: info.env_id.clone(),
            obs_dim: info.obs_dim,
            action_dim: info.action_dim,
            curriculum_addr: info.curriculum_addr.clone(),
            transport: info
                .transport_for(&request.get_ref().host_identity)
                .to_string(),
            shm_transitions_service: transitions,
            shm_policy_service: policy,
            policy_version: self.status.snapshot().policy_version,
            config_yaml: info.config_yaml.clone(),
            run_seed: info.run_seed,
            learner_hostname: info.learner_hostname.clone(),
            run_id: info.run_id.clone(),
            learner_host_identity: info.host_identity.clone(),
            action_scale: rfcl_proto::convert::action_scale_to_wire(info.action_scale.as_deref()),
        }))
    }

    async fn push_transitions(
        &self,
        request: Request<Streaming<v1::TransitionBatch>>,
    ) -> Result<Response<v1::PushSummary>, Status> {
        let mut stream = request.into_inner();
        let mut stopping = self.stopping.clone();
        let tally = StreamTally::new(self.counters.clone());
        let mut queued = 0u64;
        loop {
            let message = tokio::select! {
                m = stream.message() => m.map_err(|status| self.refuse_oversized(status))?,
                _ = stopping.wait_for(|s| *s) => return Err(shutting_down()),
            };
            let Some(batch) = message else { break };
            let max_epoch = self.status.snapshot().stage_epoch + 1;
            let info = validate_batch(&batch, self.layout, max_epoch).inspect_err(|_| {
                self.counters
                    .grpc
                    .refused_batches
                    .fetch_add(1, Ordering::Relaxed);
            })?;
            if info.count == 0 {
                continue;
            }
            let item = IngestItem::new(self.layout, batch.records, info.count, tally.clone());
            // Counted before the queue takes it, so Health never shows more stored than taken
            // in; an item the queue does not take counts itself as unused.
            self.counters.queued(Transport::Grpc, info.count as u64);
            tokio::select! {
                sent = self.ingest.send(item) => sent.map_err(|_| shutting_down())?,
                _ = stopping.wait_for(|s| *s) => return Err(shutting_down()),
            }
            queued += 1;
        }
        tokio::select! {
            _ = tally.wait_finished(queued) => {}
            _ = stopping.wait_for(|s| *s) => {}
        }
        Ok(Response::new(tally.summary()))
    }

    type WatchPolicyStream = PolicyStream;

    async fn watch_policy(
        &self,
        request: Request<v1::WatchPolicyRequest>,
    ) -> Result<Response<PolicyStream>, Status> {
        let after = request.into_inner().after_version;
        let stream = tokio_stream::wrappers::WatchStream::new(self.policy.clone())
            .filter(move |weights| weights.version > after)
            .map(|weights| {
                Ok(v1::PolicyWeights {
                    version: weights.version,
                    safetensors: weights.safetensors.clone(),
                    learner_env_steps: weights.learner_env_steps,
                })
            });
        Ok(Response::new(Box::pin(stream)))
    }

    async fn health(
        &self,
        _: Request<v1::HealthRequest>,
    ) -> Result<Response<v1::HealthReply>, Status> {
        let s = self.status.snapshot();
        let t = self.counters.totals();
        Ok(Response::new(v1::HealthReply {
            ok: !self.status.failed.load(Ordering::Relaxed),
            updates: s.critic_updates,
            env_steps: s.env_steps,
            policy_version: s.policy_version,
            grpc_records: t.grpc_records,
            grpc_batches: t.grpc_batches,
            shm_records: t.shm_records,
            shm_batches: t.shm_batches,
            shm_lost_records: t.shm_lost_records,
            refused_batches: t.refused_batches,
            dropped_stale_epoch: s.dropped_stale_epoch,
            unused_records: t.unused_records,
            unauthenticated_calls: self.guard.refused(),
            run_id: self.info.run_id.clone(),
            window: self.status.window().map(|w| window_to_wire(&w)),
        }))
    }
}

/// The learner's last progress window as `HealthReply.window`.
fn window_to_wire(w: &WindowStats) -> v1::LearnerWindow {
    let [critic_loss, q, actor_loss, entropy, temperature, _temp_loss] = w.update_means;
    v1::LearnerWindow {
        seconds: w.seconds,
        updates_per_s: w.updates_per_s,
        env_steps_per_s: w.env_steps_per_s,
        utd: w.utd,
        utd_target: w.utd_target,
        policy_lag_max: w.policy_lag_max,
        critic_loss,
        q,
        actor_loss,
        entropy,
        temperature,
        wait_s: w.timings.wait,
        ingest_s: w.timings.ingest,
        update_s: w.timings.update,
        publish_s: w.timings.publish,
        checkpoint_s: w.timings.checkpoint,
    }
}

/// Serves the learner service on `listener` until `shutdown` resolves: every call must carry the
/// run's token (`auth`), and the standard health service answers probes.
pub async fn serve(
    listener: TcpListener,
    service: LearnerService,
    auth: ServerAuth,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), tonic::transport::Error> {
    let (reporter, health) = health::health_reporter();
    health::serving(
        &reporter,
        <LearnerServer<LearnerService> as NamedService>::NAME,
    )
    .await;
    rfcl_proto::link::server(auth.server()?)
        .tcp_nodelay(true)
        .initial_stream_window_size(STREAM_WINDOW_BYTES)
        .initial_connection_window_size(CONNECTION_WINDOW_BYTES)
        .add_service(health)
        .add_service(InterceptedService::new(service.into_server(), auth.guard))
        .serve_with_incoming_shutdown(
            tokio_stream::wrappers::TcpListenerStream::new(listener),
            shutdown,
        )
        .await
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::Timings;

    #[test]
    fn the_window_goes_on_the_wire_with_each_update_mean_in_its_field() {
        let w = WindowStats {
            seconds: 10.0,
            updates_per_s: 40.0,
            env_steps_per_s: 2.5,
            utd: 15.5,
            utd_target: 16.0,
            policy_lag_max: 3,
            update_means: [
                Some(1.0),
                Some(2.0),
                Some(3.0),
                Some(4.0),
                Some(0.5),
                Some(6.0),
            ],
            timings: Timings {
                wait: 1.0,
                ingest: 0.5,
                update: 8.0,
                publish: 0.25,
                checkpoint: 0.125,
            },
        };
        let wire = window_to_wire(&w);
        assert_eq!(
            (
                wire.critic_loss,
                wire.q,
                wire.actor_loss,
                wire.entropy,
                wire.temperature
            ),
            (Some(1.0), Some(2.0), Some(3.0), Some(4.0), Some(0.5))
        );
        assert_eq!(
            (wire.seconds, wire.updates_per_s, wire.policy_lag_max),
            (10.0, 40.0, 3)
        );
        assert_eq!(
            (
                wire.wait_s,
                wire.ingest_s,
                wire.update_s,
                wire.publish_s,
                wire.checkpoint_s
            ),
            (1.0, 0.5, 8.0, 0.25, 0.125)
        );
        let idle = window_to_wire(&WindowStats::default());
        assert_eq!(idle.critic_loss, None);
    }
}
