//! The actor's connections: the learner (run description, transition stream, policy stream) and
//! the curriculum server (Acquire, Report). Every call retries a lost connection with backoff and
//! logs it; an outage longer than `--retry-for` is a clear error, never a hang.
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::retry::Backoff;
use anyhow::{anyhow, bail, Context, Result};
use rfcl_core::lease::{AcquireRequest, EpisodeReport, ResetLease};
use rfcl_core::video::EvalVideo;
use rfcl_proto::auth::{AuthChannel, ClientAuth};
use rfcl_proto::v1;
use rfcl_proto::v1::curriculum_client::CurriculumClient;
use rfcl_proto::v1::eval_videos_client::EvalVideosClient;
use rfcl_proto::v1::learner_client::LearnerClient;
use tokio::sync::{mpsc, watch};
use tonic::transport::Endpoint;
use tonic::{Code, Status};

/// The largest reply accepted from the curriculum server: its own limit on what it sends (a lease
/// carries one env state, a few KiB).
const CURRICULUM_REPLY_BYTES: usize = 16 << 20;
/// The largest unary reply accepted from the learner (RunInfo with the resolved config, Health).
const LEARNER_REPLY_BYTES: usize = 4 << 20;
/// A PolicyWeights message beyond its safetensors bytes: version, env steps, framing.
const POLICY_MESSAGE_MARGIN: usize = 64 << 10;
/// What the policy stream accepts until the run's policy size is known
/// ([`Learner::expect_policies_of`]), and the most a TransitionBatch may be encoded to (batches
/// are bounded by `service.transition_batch`; the learner refuses, and counts, larger ones).
const MAX_MESSAGE_BYTES: usize = 256 << 20;
/// One unary call may take this long before it counts as failed.
const CALL_TIMEOUT: Duration = Duration::from_secs(15);

/// `127.0.0.1:50051` or `http://127.0.0.1:50051` → an endpoint URI.
pub fn normalize_addr(addr: &str) -> String {
    if addr.contains("://") {
        addr.to_string()
    } else {
        format!("http://{addr}")
    }
}

/// A lazily connected channel whose calls carry the run's token: it (re)connects on use, so a
/// call after an outage tries again.
pub fn channel(addr: &str, auth: &ClientAuth, unary_timeout: bool) -> Result<AuthChannel> {
    let uri = normalize_addr(addr);
    let endpoint = Endpoint::from_shared(uri.clone())
        .with_context(|| format!("invalid address {addr:?}"))?
        .connect_timeout(Duration::from_secs(3))
        .tcp_nodelay(true);
    let mut endpoint = rfcl_proto::link::client(endpoint);
    if unary_timeout {
        endpoint = endpoint.timeout(CALL_TIMEOUT);
    }
    let endpoint = auth
        .endpoint(endpoint)
        .with_context(|| format!("TLS for {addr:?}"))?;
    Ok(auth.wrap(endpoint.connect_lazy()))
}

/// Statuses that mean "the connection, not the request, failed": retried.
pub fn is_transient(status: &Status) -> bool {
    matches!(
        status.code(),
        Code::Unavailable | Code::Unknown | Code::Cancelled | Code::DeadlineExceeded
    )
}

/// How an actor retries: 100 ms doubling to 2 s, for at most `retry_for`.
pub fn backoff(retry_for: Duration) -> Backoff {
    Backoff::new(
        Duration::from_millis(100),
        Duration::from_secs(2),
        retry_for,
    )
}

/// Runs `call` until it succeeds or fails for a reason other than the connection; retries
/// transient failures with backoff, logging each, for at most `retry_for`.
pub async fn retrying<T, F, Fut>(
    peer: &str,
    what: &str,
    retry_for: Duration,
    mut call: F,
) -> Result<std::result::Result<T, Status>>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = std::result::Result<T, Status>>,
{
    let mut backoff = backoff(retry_for);
    loop {
        match call().await {
            Err(status) if is_transient(&status) => {
                let Some(delay) = backoff.next_delay(Instant::now()) else {
                    bail!(
                        "{peer} unreachable for {:.0} s ({what}): {}",
                        retry_for.as_secs_f64(),
                        status.message()
                    );
                };
                tracing::warn!(
                    attempt = backoff.attempts(),
                    "{what}: {peer} unreachable ({}); retrying in {} ms",
                    status.message(),
                    delay.as_millis()
                );
                tokio::time::sleep(delay).await;
            }
            done => {
                if backoff.attempts() > 0 {
                    tracing::info!("{what}: {peer} reachable again");
                }
                return Ok(done);
            }
        }
    }
}

/// The curriculum server as an actor uses it.
pub struct Curriculum {
    client: CurriculumClient<AuthChannel>,
    videos: EvalVideosClient<AuthChannel>,
    peer: String,
    retry_for: Duration,
}

/// What became of an episode report.
#[derive(Debug, Clone, PartialEq)]
pub enum Reported {
    /// Applied (or a repeat of an applied report: acknowledged, nothing changed).
    Acked { applied: bool, stage_epoch: u64 },
    /// Refused and counted by the server (expired lease, ended stage epoch, unknown lease).
    Refused(String),
}

impl Curriculum {
    pub fn new(addr: &str, auth: &ClientAuth, retry_for: Duration) -> Result<Self> {
        let channel = channel(addr, auth, true)?;
        Ok(Self {
            client: CurriculumClient::new(channel.clone())
                .max_decoding_message_size(CURRICULUM_REPLY_BYTES),
            videos: EvalVideosClient::new(channel),
            peer: format!("curriculum server at {}", normalize_addr(addr)),
            retry_for,
        })
    }

    /// Whether the curriculum server says the run is over (its current stage announcement);
    /// false when it cannot say within a few seconds.
    pub async fn finished(&self) -> bool {
        let mut c = self.client.clone();
        let first = async move {
            let mut stream = c
                .watch_stage(v1::WatchStageRequest::default())
                .await
                .ok()?
                .into_inner();
            stream.message().await.ok().flatten()
        };
        matches!(
            tokio::time::timeout(Duration::from_secs(5), first).await,
            Ok(Some(event)) if event.finished
        )
    }

    /// A reset lease, or `None` once the curriculum has finished (stage 1 only, spec 2.7).
    pub async fn acquire(&self, req: AcquireRequest) -> Result<Option<ResetLease>> {
        let wire = v1::AcquireRequest::from(req);
        let result = retrying(&self.peer, "Acquire", self.retry_for, || {
            let mut c = self.client.clone();
            let w = wire;
            async move { c.acquire(w).await }
        })
        .await?;
        match result {
            Ok(lease) => Ok(Some(
                ResetLease::try_from(lease.into_inner())
                    .with_context(|| format!("the {} sent a malformed lease", self.peer))?,
            )),
            Err(status) if status.code() == Code::FailedPrecondition => {
                tracing::info!("the curriculum has finished: {}", status.message());
                Ok(None)
            }
            Err(status) => Err(anyhow!(
                "Acquire refused by the {}: {}",
                self.peer,
                status.message()
            )),
        }
    }

    /// Reports an episode and takes the next lease for `next` in one round trip. A refused
    /// report hands out no lease (the caller acquires one); so does a finished curriculum. A retry
    /// after a lost answer re-applies nothing (the report is a repeat) but takes a new lease: the
    /// lease of the lost answer expires on the server, counted there.
    pub async fn report_and_acquire(
        &self,
        report: &EpisodeReport,
        next: AcquireRequest,
    ) -> Result<(Reported, Option<ResetLease>)> {
        let wire = v1::ReportAndAcquireRequest {
            report: Some(v1::EpisodeReport::from(report.clone())),
            next: Some(v1::AcquireRequest::from(next)),
        };
        let result = retrying(&self.peer, "ReportAndAcquire", self.retry_for, || {
            let (mut c, wire) = (self.client.clone(), wire.clone());
            async move { c.report_and_acquire(wire).await }
        })
        .await?;
        match result {
            Ok(reply) => {
                let reply = reply.into_inner();
                let ack = reply.ack.unwrap_or_default();
                let lease = reply
                    .lease
                    .map(ResetLease::try_from)
                    .transpose()
                    .with_context(|| format!("the {} sent a malformed lease", self.peer))?;
                Ok((
                    Reported::Acked {
                        applied: ack.applied,
                        stage_epoch: ack.stage_epoch,
                    },
                    lease,
                ))
            }
            Err(status) => Ok((self.refusal(report, status)?, None)),
        }
    }

    fn refusal(&self, report: &EpisodeReport, status: Status) -> Result<Reported> {
        match status.code() {
            Code::FailedPrecondition | Code::NotFound | Code::AlreadyExists => {
                Ok(Reported::Refused(status.message().to_string()))
            }
            _ => Err(anyhow!(
                "Report of lease {} refused by the {}: {}",
                report.lease_id,
                self.peer,
                status.message()
            )),
        }
    }

    /// The learner's env steps at the publication of the newest policy whose evaluation is
    /// complete (0: none), where a (re)started eval actor's schedule goes on from.
    pub async fn last_complete_eval(&self) -> Result<u64> {
        let result = retrying(&self.peer, "GetState", self.retry_for, || {
            let mut c = self.client.clone();
            async move { c.get_state(v1::GetStateRequest {}).await }
        })
        .await?;
        match result {
            Ok(state) => Ok(state.into_inner().last_complete_eval_env_steps),
            Err(status) => bail!(
                "GetState refused by the {}: {}",
                self.peer,
                status.message()
            ),
        }
    }

    /// Sends a recorded eval episode; the name the dashboard serves it under.
    pub async fn put_video(&self, video: EvalVideo) -> Result<String> {
        let wire = v1::EvalVideo::from(video);
        let result = retrying(&self.peer, "EvalVideos.Put", self.retry_for, || {
            let mut c = self.videos.clone();
            let wire = wire.clone();
            async move { c.put(wire).await }
        })
        .await?;
        match result {
            Ok(ack) => Ok(ack.into_inner().name),
            Err(status) => bail!(
                "the {} refused the eval video: {}",
                self.peer,
                status.message()
            ),
        }
    }

    /// Reports an episode exactly once: a retried report that the server already applied is
    /// acknowledged without change.
    pub async fn report(&self, report: &EpisodeReport) -> Result<Reported> {
        let wire = v1::EpisodeReport::from(report.clone());
        let result = retrying(&self.peer, "Report", self.retry_for, || {
            let (mut c, wire) = (self.client.clone(), wire.clone());
            async move { c.report(wire).await }
        })
        .await?;
        match result {
            Ok(ack) => {
                let ack = ack.into_inner();
                Ok(Reported::Acked {
                    applied: ack.applied,
                    stage_epoch: ack.stage_epoch,
                })
            }
            Err(status) => self.refusal(report, status),
        }
    }
}

/// The learner as an actor uses it.
#[derive(Clone)]
pub struct Learner {
    client: LearnerClient<AuthChannel>,
    streams: LearnerClient<AuthChannel>,
    pub peer: String,
    retry_for: Duration,
}

impl Learner {
    pub fn new(addr: &str, auth: &ClientAuth, retry_for: Duration) -> Result<Self> {
        let unary = LearnerClient::new(channel(addr, auth, true)?);
        // Streams live for the whole run: no per-call timeout on their channel.
        let streams = LearnerClient::new(channel(addr, auth, false)?);
        Ok(Self {
            client: unary.max_decoding_message_size(LEARNER_REPLY_BYTES),
            streams: streams
                .max_decoding_message_size(MAX_MESSAGE_BYTES)
                .max_encoding_message_size(MAX_MESSAGE_BYTES),
            peer: format!("learner at {}", normalize_addr(addr)),
            retry_for,
        })
    }

    /// Bounds the policy stream by the run's policy size `policy_bytes` (every version of a run
    /// has the same size), with a 2x margin for a learner built with another safetensors
    /// version: a learner cannot make this actor buffer much more than a policy's worth.
    pub fn expect_policies_of(mut self, policy_bytes: usize) -> Self {
        self.streams = self
            .streams
            .max_decoding_message_size(2 * policy_bytes + POLICY_MESSAGE_MARGIN);
        self
    }

    pub async fn run_info(&self, actor_id: u32) -> Result<v1::RunInfo> {
        let hostname = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_default();
        let req = v1::GetRunInfoRequest {
            actor_id,
            hostname,
            host_identity: rfcl_shm::host_identity(),
        };
        let result = retrying(&self.peer, "GetRunInfo", self.retry_for, || {
            let mut c = self.client.clone();
            let r = req.clone();
            async move { c.get_run_info(r).await }
        })
        .await?;
        result
            .map(|r| r.into_inner())
            .map_err(|s| anyhow!("GetRunInfo refused by the {}: {}", self.peer, s.message()))
    }

    /// Returns an error once the learner has been unreachable for `retry_for` (checked with
    /// Health every `every`). Over shared memory nothing else notices a dead learner: a gRPC
    /// actor's policy stream does.
    pub async fn watch_alive(&self, every: Duration, run_id: &str) -> Result<()> {
        loop {
            tokio::time::sleep(every).await;
            let result = retrying(&self.peer, "Health", self.retry_for, || {
                let mut c = self.client.clone();
                async move { c.health(v1::HealthRequest {}).await }
            })
            .await?;
            let health = match result {
                Ok(reply) => reply.into_inner(),
                Err(status) => bail!("Health refused by the {}: {}", self.peer, status.message()),
            };
            // A restarted learner serves new shared-memory services: this actor's ports lead to
            // the old ones, which nobody reads any more.
            if health.run_id != run_id {
                bail!(
                    "the {} restarted (session {run_id} is now {}): its shared-memory services \
                     are new, so this actor stops to be started again on them",
                    self.peer,
                    health.run_id
                );
            }
        }
    }

    /// Keeps `latest` at the newest policy the learner published, re-subscribing after a lost
    /// connection. Returns an error once the learner has been unreachable for `retry_for`.
    pub async fn watch_policy(
        &self,
        latest: watch::Sender<Option<Arc<v1::PolicyWeights>>>,
    ) -> Result<()> {
        let mut backoff = backoff(self.retry_for);
        let mut after_version = 0;
        loop {
            let mut client = self.streams.clone();
            let error = match client
                .watch_policy(v1::WatchPolicyRequest { after_version })
                .await
            {
                Ok(stream) => {
                    let mut stream = stream.into_inner();
                    loop {
                        match stream.message().await {
                            Ok(Some(weights)) => {
                                if backoff.attempts() > 0 {
                                    tracing::info!("WatchPolicy: {} reachable again", self.peer);
                                }
                                backoff.reset();
                                tracing::debug!(
                                    version = weights.version,
                                    env_steps = weights.learner_env_steps,
                                    "new policy"
                                );
                                after_version = after_version.max(weights.version);
                                latest.send_replace(Some(Arc::new(weights)));
                            }
                            Ok(None) => {
                                break Status::unavailable("the policy stream ended");
                            }
                            Err(status) => break status,
                        }
                    }
                }
                Err(status) => status,
            };
            if !is_transient(&error) {
                bail!(
                    "WatchPolicy refused by the {}: {}",
                    self.peer,
                    error.message()
                );
            }
            let Some(delay) = backoff.next_delay(Instant::now()) else {
                bail!(
                    "{} unreachable for {:.0} s (WatchPolicy): {}",
                    self.peer,
                    self.retry_for.as_secs_f64(),
                    error.message()
                );
            };
            tracing::warn!(
                "WatchPolicy: lost the {} ({}); retrying in {} ms",
                self.peer,
                error.message(),
                delay.as_millis()
            );
            tokio::time::sleep(delay).await;
        }
    }

    /// Streams the batches from `batches` to the learner over PushTransitions, in acknowledged
    /// windows: a stream carries at most [`PUSH_WINDOW_BATCHES`] batches, is closed, and the
    /// learner's answer (sent once it has handled every batch of the stream) confirms them before
    /// the next window opens. So an actor runs at most a window (plus its small queue) ahead of the
    /// learner, whatever HTTP/2's flow-control windows would allow (about 1 MB per stream), and the
    /// transitions at risk when a stream breaks are exactly those of one window: they are counted
    /// in `counters` as unconfirmed. The learner holds actors back by not reading (sync UTD mode):
    /// a full `batches` channel blocks the env loop.
    ///
    /// Returns when `batches` closes (after the learner answered) or with an error once the
    /// learner has been unreachable for `retry_for`.
    pub async fn push_transitions(
        &self,
        mut batches: mpsc::Receiver<v1::TransitionBatch>,
        counters: Arc<PushCounters>,
    ) -> Result<()> {
        let mut backoff = backoff(self.retry_for);
        // A batch taken from `batches` whose stream broke before it went out.
        let mut carry: Option<v1::TransitionBatch> = None;
        let mut closing = false;
        loop {
            let (tx, rx) = mpsc::channel::<v1::TransitionBatch>(PUSH_WINDOW_BATCHES);
            let mut client = self.streams.clone();
            let call = client.push_transitions(tokio_stream::wrappers::ReceiverStream::new(rx));
            tokio::pin!(call);
            let mut on_stream = 0u64;
            let mut in_window = 0usize;
            let mut tx = Some(tx);
            let outcome = loop {
                if in_window == PUSH_WINDOW_BATCHES || closing {
                    // Close the stream: the answer confirms the window.
                    tx = None;
                }
                let Some(open) = tx.as_ref() else {
                    break (&mut call).await;
                };
                let next = async {
                    match carry.take() {
                        Some(b) => Some(b),
                        None => batches.recv().await,
                    }
                };
                tokio::select! {
                    res = &mut call => break res,
                    batch = next => match batch {
                        Some(batch) => {
                            let count = u64::from(batch.count);
                            match open.send(batch).await {
                                Ok(()) => {
                                    on_stream += count;
                                    in_window += 1;
                                    counters.sent.fetch_add(count, Ordering::Relaxed);
                                }
                                // The stream broke: keep the batch for the next one.
                                Err(mpsc::error::SendError(batch)) => carry = Some(batch),
                            }
                        }
                        None => closing = true,
                    },
                }
            };
            drop(tx);
            match outcome {
                Ok(summary) => {
                    let s = summary.into_inner();
                    counters.accepted.fetch_add(s.accepted, Ordering::Relaxed);
                    counters
                        .dropped_stale_epoch
                        .fetch_add(s.dropped_stale_epoch, Ordering::Relaxed);
                    let confirmed = s.accepted + s.dropped_stale_epoch;
                    if confirmed < on_stream {
                        counters
                            .unconfirmed
                            .fetch_add(on_stream - confirmed, Ordering::Relaxed);
                        tracing::warn!(
                            sent = on_stream,
                            confirmed,
                            "PushTransitions: the {} answered before taking every transition",
                            self.peer
                        );
                    }
                    if backoff.attempts() > 0 {
                        tracing::info!("PushTransitions: {} reachable again", self.peer);
                        backoff.reset();
                    }
                    if closing && carry.is_none() {
                        return Ok(());
                    }
                }
                Err(status) => {
                    counters.unconfirmed.fetch_add(on_stream, Ordering::Relaxed);
                    if on_stream > 0 {
                        tracing::warn!(
                            "PushTransitions: the stream to the {} broke with {on_stream} \
                             transitions on it unconfirmed ({})",
                            self.peer,
                            status.message()
                        );
                    }
                    if !is_transient(&status) {
                        bail!(
                            "PushTransitions refused by the {}: {}",
                            self.peer,
                            status.message()
                        );
                    }
                    if closing && carry.is_none() {
                        return Ok(());
                    }
                    let Some(delay) = backoff.next_delay(Instant::now()) else {
                        bail!(
                            "{} unreachable for {:.0} s (PushTransitions): {}",
                            self.peer,
                            self.retry_for.as_secs_f64(),
                            status.message()
                        );
                    };
                    tracing::warn!(
                        "PushTransitions: retrying the {} in {} ms",
                        self.peer,
                        delay.as_millis()
                    );
                    tokio::time::sleep(delay).await;
                }
            }
        }
    }
}

/// Batches per acknowledged PushTransitions stream (see [`Learner::push_transitions`]).
pub const PUSH_WINDOW_BATCHES: usize = 2;

/// What the transition stream did, over all its reconnections.
#[derive(Debug, Default)]
pub struct PushCounters {
    /// Transitions handed to an open stream.
    pub sent: AtomicU64,
    /// Transitions the learner confirmed as stored (its PushSummary).
    pub accepted: AtomicU64,
    /// Transitions on a stream that broke before the learner confirmed it: possibly lost.
    pub unconfirmed: AtomicU64,
    /// Transitions the learner dropped as from an ended stage epoch (its PushSummary).
    pub dropped_stale_epoch: AtomicU64,
    /// Transitions this actor gave up sending (shared memory: the learner stopped receiving, or
    /// the actor stopped while the learner held it back). Counted, never silent.
    pub given_up: AtomicU64,
}
