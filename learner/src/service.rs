//! The `rfcl.v1.Learner` gRPC service: a thin shell over the training thread.
//!
//! * `GetRunInfo`: the run description actors start from (dims, env id, curriculum address,
//!   transport, resolved config as YAML, run seed, the learner's host).
//! * `PushTransitions`: client stream of validated [`TransitionBatch`](v1::TransitionBatch)es into
//!   the bounded ingest queue. When the training thread falls behind (the `sync` UTD limiter), the
//!   queue fills, this handler stops reading its stream and HTTP/2 flow control holds the actor
//!   back. The answer, once the stream closed and every batch of it was handled, gives exact
//!   counts: records stored and records dropped because their stage epoch had ended.
//! * `WatchPolicy`: the current version first when newer than `after_version`, then each newer one
//!   as it is published. Versions are immutable `Arc`s in a `watch` channel: a reader never sees a
//!   torn version, and a slow reader skips straight to the latest. The stream ends when training
//!   ends.
//! * `Health`: critic updates (`updates`), env steps received and stored, policy version, read
//!   together at one consistent point of the training loop; `ok` is false once training failed.
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use rfcl_core::transition::RecordLayout;
use rfcl_proto::v1;
use rfcl_proto::v1::learner_server::{Learner, LearnerServer};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

use crate::ingest::{validate_batch, IngestItem, StreamTally};
use crate::trainer::LearnerStatus;

/// Largest gRPC message accepted or sent (transition batches, policy weights of wide networks).
pub const MAX_MESSAGE_BYTES: usize = 256 << 20;

/// The run description `GetRunInfo` answers with (its dynamic part, the policy version, comes
/// from the training thread).
#[derive(Debug, Clone, PartialEq)]
pub struct RunDescription {
    pub run_name: String,
    pub env_id: String,
    pub obs_dim: u32,
    pub action_dim: u32,
    pub curriculum_addr: String,
    /// "grpc": this learner ingests and publishes over gRPC only.
    pub transport: String,
    pub config_yaml: String,
    pub run_seed: u64,
    pub learner_hostname: String,
}

#[derive(Clone)]
pub struct LearnerService {
    info: Arc<RunDescription>,
    layout: RecordLayout,
    status: Arc<LearnerStatus>,
    ingest: mpsc::Sender<IngestItem>,
    policy: watch::Receiver<Arc<v1::PolicyWeights>>,
    /// True once the learner is shutting down: open streams are answered and closed.
    stopping: watch::Receiver<bool>,
}

impl LearnerService {
    pub fn new(
        info: RunDescription,
        status: Arc<LearnerStatus>,
        ingest: mpsc::Sender<IngestItem>,
        policy: watch::Receiver<Arc<v1::PolicyWeights>>,
        stopping: watch::Receiver<bool>,
    ) -> Self {
        let layout = RecordLayout::new(info.obs_dim as usize, info.action_dim as usize);
        Self {
            info: Arc::new(info),
            layout,
            status,
            ingest,
            policy,
            stopping,
        }
    }

    /// The tonic service with this crate's message limits.
    pub fn into_server(self) -> LearnerServer<Self> {
        LearnerServer::new(self)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
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
        _: Request<v1::GetRunInfoRequest>,
    ) -> Result<Response<v1::RunInfo>, Status> {
        let info = &self.info;
        Ok(Response::new(v1::RunInfo {
            run_name: info.run_name.clone(),
            env_id: info.env_id.clone(),
            obs_dim: info.obs_dim,
            action_dim: info.action_dim,
            curriculum_addr: info.curriculum_addr.clone(),
            transport: info.transport.clone(),
            shm_transitions_service: String::new(),
            shm_policy_service: String::new(),
            policy_version: self.status.snapshot().policy_version,
            config_yaml: info.config_yaml.clone(),
            run_seed: info.run_seed,
            learner_hostname: info.learner_hostname.clone(),
        }))
    }

    async fn push_transitions(
        &self,
        request: Request<Streaming<v1::TransitionBatch>>,
    ) -> Result<Response<v1::PushSummary>, Status> {
        let mut stream = request.into_inner();
        let mut stopping = self.stopping.clone();
        let tally = StreamTally::new();
        let mut queued = 0u64;
        loop {
            let message = tokio::select! {
                m = stream.message() => m?,
                _ = stopping.wait_for(|s| *s) => return Err(shutting_down()),
            };
            let Some(batch) = message else { break };
            let max_epoch = self.status.snapshot().stage_epoch + 1;
            let info = validate_batch(&batch, self.layout, max_epoch)?;
            if info.count == 0 {
                continue;
            }
            let item = IngestItem::new(self.layout, batch.records, info.count, tally.clone());
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
            .map(|weights| Ok(v1::PolicyWeights::clone(&weights)));
        Ok(Response::new(Box::pin(stream)))
    }

    async fn health(
        &self,
        _: Request<v1::HealthRequest>,
    ) -> Result<Response<v1::HealthReply>, Status> {
        let s = self.status.snapshot();
        Ok(Response::new(v1::HealthReply {
            ok: !self.status.failed.load(Ordering::Relaxed),
            updates: s.critic_updates,
            env_steps: s.env_steps,
            policy_version: s.policy_version,
        }))
    }
}

/// Serves the learner service on `listener` until `shutdown` resolves.
pub async fn serve(
    listener: TcpListener,
    service: LearnerService,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), tonic::transport::Error> {
    tonic::transport::Server::builder()
        .tcp_nodelay(true)
        .add_service(service.into_server())
        .serve_with_incoming_shutdown(
            tokio_stream::wrappers::TcpListenerStream::new(listener),
            shutdown,
        )
        .await
}
