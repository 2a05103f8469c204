//! The learner's same-host transport (docs/DESIGN.md, "Processes"): transition frames from actors on
//! this host over iceoryx2 shared memory into the *same* ingest queue as `PushTransitions`, and
//! every policy version out to them.
//!
//! * **Ingest thread** (`shm-ingest`): takes frames from the run's transition service as they
//!   arrive, checks each with [`validate_records`] (exactly the gRPC checks: dims, lengths, finite
//!   numbers, mask, action range, stage epoch), copies the records out of shared memory into an
//!   [`IngestItem`] and blocks on the bounded queue. So the training thread sees no difference:
//!   the same stale-epoch drops and the same UTD limiter. At most [`MAX_QUEUED`] of its frames
//!   wait in the queue at once (as the gRPC path's acknowledged windows bound a stream): when the
//!   limiter holds the queue, this thread stops taking frames, the service's small per-actor
//!   queue fills and the actors' publishers wait (back-pressure; the service never overwrites,
//!   see `rfcl_shm::ports`). So a same-host actor runs only a few batches ahead of the learner,
//!   which keeps the policy lag as small as over gRPC. Frames carry a
//!   per-publisher sequence number and record count: a gap is counted in
//!   [`TransportCounts::lost_records`](crate::ingest::TransportCounts) and logged. A malformed
//!   frame is counted as refused and logged (an actor cannot be answered over shared memory).
//! * **Policy thread** (`shm-policy`): publishes the current version at start and then each new
//!   one from the trainer's `watch` channel, as one immutable sample shared by every subscriber.
//!
//! Both threads end when the learner stops (the ingest thread also when the queue closes).
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use rfcl_core::transition::RecordLayout;
use rfcl_shm::{
    Cleanup, PolicyHeader, PolicyLimits, PolicyPublisher, ServiceNames, ShmError, ShmNode,
    TransitionLimits, TransitionSubscriber,
};
use tokio::sync::{mpsc, watch};

use crate::ingest::{
    validate_records, IngestCounters, IngestItem, RecordsHeader, StreamTally, Transport,
};
use crate::trainer::{LearnerStatus, PolicyWatch};

/// Names shared-memory frames in validation errors.
const FRAME: &str = "shared-memory transition frame";
/// How long the ingest thread sleeps when no frame is queued (after a short spin).
const IDLE_SLEEP: Duration = Duration::from_micros(200);
/// How often refused frames and gaps are logged at most (each is counted always).
const WARN_EVERY: Duration = Duration::from_secs(10);
/// How often the policy thread connects new subscribers while no new version comes.
const CONNECT_EVERY: Duration = Duration::from_millis(20);
/// Shared-memory frames queued for the training thread at most (not yet handled).
pub const MAX_QUEUED: u64 = 2;

/// What the learner's shared-memory transport needs.
pub struct ShmSetup {
    pub run_name: String,
    pub run_id: String,
    pub layout: RecordLayout,
    /// Bytes of the policy's safetensors (sizes the policy samples).
    pub policy_bytes: usize,
    pub transitions: TransitionLimits,
    pub policy: PolicyLimits,
}

/// The running transport: its service names and threads.
pub struct ShmTransport {
    pub names: ServiceNames,
    threads: Vec<JoinHandle<()>>,
}

impl ShmTransport {
    /// Creates the run's two services (cleaning up dead nodes of earlier processes first) and
    /// starts the ingest and policy threads. Errors name the service.
    #[allow(clippy::too_many_arguments)]
    pub fn start(
        setup: ShmSetup,
        status: Arc<LearnerStatus>,
        ingest: mpsc::Sender<IngestItem>,
        policy: PolicyWatch,
        counters: Arc<IngestCounters>,
        stopping: watch::Receiver<bool>,
        runtime: tokio::runtime::Handle,
    ) -> Result<Self, ShmError> {
        let names = ServiceNames::new(&setup.run_name, &setup.run_id);
        let (ingest_node, cleanup) = ShmNode::create(&setup.run_name, "learner-ingest")?;
        log_cleanup(&setup.run_name, cleanup);
        let subscriber =
            TransitionSubscriber::create(ingest_node, &names.transitions, setup.transitions)?;
        let (policy_node, _) = ShmNode::create(&setup.run_name, "learner-policy")?;
        let publisher =
            PolicyPublisher::create(policy_node, &names.policy, setup.policy, setup.policy_bytes)?;
        tracing::info!(
            transitions = %names.transitions,
            policy = %names.policy,
            max_actors = setup.transitions.max_publishers,
            queue_frames = setup.transitions.queue_frames,
            "shared-memory services ready (iceoryx2)"
        );
        let policy_runtime = runtime.clone();
        let ingest_thread = {
            let stopping = stopping.clone();
            let layout = setup.layout;
            std::thread::Builder::new()
                .name("shm-ingest".into())
                .spawn(move || {
                    IngestLoop {
                        subscriber,
                        layout,
                        status,
                        ingest,
                        tally: StreamTally::new(counters.clone()),
                        counters,
                        queued: 0,
                        runtime,
                        expected: HashMap::new(),
                        last_warning: None,
                    }
                    .run(stopping)
                })
                .map_err(|e| thread_error(&names.transitions, e))?
        };
        let policy_thread = std::thread::Builder::new()
            .name("shm-policy".into())
            .spawn(move || publish_policies(publisher, policy, stopping, policy_runtime))
            .map_err(|e| thread_error(&names.policy, e))?;
        Ok(Self {
            names,
            threads: vec![ingest_thread, policy_thread],
        })
    }

    /// Waits (at most `limit`) for both threads to end once the learner stops; their nodes then
    /// remove the services' files.
    pub fn join(self, limit: Duration) {
        let until = Instant::now() + limit;
        for thread in self.threads {
            while !thread.is_finished() && Instant::now() < until {
                std::thread::sleep(Duration::from_millis(10));
            }
            if thread.is_finished() {
                if thread.join().is_err() {
                    tracing::warn!("a shared-memory thread panicked");
                }
            } else {
                tracing::warn!("a shared-memory thread did not stop within {limit:?}");
            }
        }
    }
}

impl ShmTransport {
    /// [`ShmTransport::start`] for the run `info` describes, with the default limits, on the
    /// current tokio runtime (the `learner` binary's one call).
    pub fn start_for(
        info: &crate::service::RunDescription,
        layout: RecordLayout,
        status: &Arc<LearnerStatus>,
        ingest: &mpsc::Sender<IngestItem>,
        policy: &PolicyWatch,
        counters: &Arc<IngestCounters>,
        stopping: &watch::Receiver<bool>,
    ) -> Result<Self, ShmError> {
        let policy_bytes = policy.borrow().safetensors.len();
        Self::start(
            ShmSetup {
                run_name: info.run_name.clone(),
                run_id: info.run_id.clone(),
                layout,
                policy_bytes,
                transitions: TransitionLimits::default(),
                policy: PolicyLimits::default(),
            },
            status.clone(),
            ingest.clone(),
            policy.clone(),
            counters.clone(),
            stopping.clone(),
            tokio::runtime::Handle::current(),
        )
    }
}

fn thread_error(service: &str, source: std::io::Error) -> ShmError {
    ShmError::Thread {
        service: service.to_string(),
        source,
    }
}

fn log_cleanup(run_name: &str, cleanup: Cleanup) {
    if cleanup.of_run + cleanup.others + cleanup.failed > 0 {
        tracing::info!(
            of_this_run = cleanup.of_run,
            of_other_runs = cleanup.others,
            failed = cleanup.failed,
            "shared memory: removed the stale files of dead iceoryx2 nodes (run '{run_name}')"
        );
    }
}

/// Where the next frame of one publisher must continue.
#[derive(Debug, Clone, Copy, Default)]
struct Expected {
    seq: u64,
    records_before: u64,
}

struct IngestLoop {
    subscriber: TransitionSubscriber,
    layout: RecordLayout,
    status: Arc<LearnerStatus>,
    ingest: mpsc::Sender<IngestItem>,
    counters: Arc<IngestCounters>,
    /// One tally for the whole transport: the training thread counts stored and stale records
    /// into it as for a gRPC stream.
    tally: Arc<StreamTally>,
    /// Frames handed to the queue so far (the tally counts those handled).
    queued: u64,
    runtime: tokio::runtime::Handle,
    /// Per publisher (a random id per actor process run).
    expected: HashMap<u64, Expected>,
    last_warning: Option<Instant>,
}

impl IngestLoop {
    /// Takes every frame the service holds now into `pending` (copied out, so the shared memory
    /// goes back at once). iceoryx2's `receive` looks at its publishers in a fixed order, so taking
    /// one frame at a time lets a publisher that always has a frame ready starve the others
    /// (measured: an actor stuck at 680 env steps while the other took 200,000). Draining all of
    /// them, then handing them on in arrival order, serves every actor once per round; `pending`
    /// never holds more than each publisher's queue (`TransitionLimits::queue_frames`).
    fn drain(&mut self, pending: &mut VecDeque<IngestItem>) -> Result<usize, rfcl_shm::ShmError> {
        let mut frames = 0;
        while let Some(frame) = self.subscriber.receive()? {
            frames += 1;
            if let Some(item) = self.take(&frame) {
                pending.push_back(item);
            }
        }
        Ok(frames)
    }

    fn run(mut self, stopping: watch::Receiver<bool>) {
        let mut idle = 0u32;
        let mut pending = VecDeque::new();
        while !*stopping.borrow() {
            if pending.is_empty() {
                match self.drain(&mut pending) {
                    Ok(0) => {
                        // Spin briefly (frames come in bursts), then sleep: short sleeps while frames
                        // were recent, longer ones once the service has been quiet for a while.
                        idle = idle.saturating_add(1);
                        match idle {
                            0..16 => std::thread::yield_now(),
                            16..512 => std::thread::sleep(IDLE_SLEEP),
                            _ => std::thread::sleep(IDLE_SLEEP * 5),
                        }
                        continue;
                    }
                    Ok(_) => idle = 0,
                    Err(e) => {
                        self.warn(format_args!("{:#}", anyhow::Error::new(e)));
                        std::thread::sleep(Duration::from_millis(10));
                        continue;
                    }
                }
            }
            let Some(item) = pending.pop_front() else {
                continue;
            };
            if self.queued >= MAX_QUEUED {
                // Items report when they are handled (or discarded at the end).
                let handled = self.queued - MAX_QUEUED + 1;
                self.runtime.block_on(self.tally.wait_finished(handled));
            }
            // Counted before the queue takes it, so Health never shows more stored than taken in.
            self.counters.queued(Transport::Shm, item.count as u64);
            self.queued += 1;
            if self.ingest.blocking_send(item).is_err() {
                // The training thread has finished; the item counted itself as unused.
                break;
            }
        }
        // Records read from shared memory but not queued yet are taken in and unused (each item
        // counts itself as it drops), so every record read is in the totals.
        for item in pending {
            self.counters.queued(Transport::Shm, item.count as u64);
        }
        let t = self.tally.summary();
        tracing::info!(
            frames = self.counters.shm.batches.load(Ordering::Relaxed),
            records = self.counters.shm.records.load(Ordering::Relaxed),
            stored = t.accepted,
            dropped_stale_epoch = t.dropped_stale_epoch,
            lost = self.counters.shm.lost_records.load(Ordering::Relaxed),
            refused_frames = self.counters.shm.refused_batches.load(Ordering::Relaxed),
            "shared-memory ingest stopped ({})",
            self.subscriber.service()
        );
    }

    /// The frame's records as an ingest item, or `None` (counted, logged) when it is malformed.
    fn take(&mut self, frame: &rfcl_shm::TransitionFrame) -> Option<IngestItem> {
        let (header, records) = match frame.decode() {
            Ok(decoded) => decoded,
            Err(e) => {
                self.refuse(format_args!("{e}"));
                return None;
            }
        };
        let expected = self.expected.entry(header.publisher).or_default();
        let gap = header
            .records_before
            .saturating_sub(expected.records_before);
        let frames_missing = header.seq.saturating_sub(expected.seq);
        *expected = Expected {
            seq: header.seq + 1,
            records_before: header.records_before + u64::from(header.count),
        };
        if gap > 0 || frames_missing > 0 {
            self.counters
                .shm
                .lost_records
                .fetch_add(gap, Ordering::Relaxed);
            tracing::warn!(
                actor = header.actor_id,
                lost_records = gap,
                lost_frames = frames_missing,
                "shared memory: frames of actor {} are missing before frame {} (the actor gave them up)",
                header.actor_id,
                header.seq
            );
        }
        let max_epoch = self.status.snapshot().stage_epoch + 1;
        let info = match validate_records(
            FRAME,
            RecordsHeader {
                obs_dim: header.obs_dim,
                action_dim: header.action_dim,
                count: header.count,
            },
            records,
            self.layout,
            max_epoch,
        ) {
            Ok(info) => info,
            Err(e) => {
                self.refuse(format_args!("actor {}: {e}", header.actor_id));
                return None;
            }
        };
        if info.count == 0 {
            return None;
        }
        Some(IngestItem::new(
            self.layout,
            records.to_vec(),
            info.count,
            self.tally.clone(),
        ))
    }

    fn refuse(&mut self, why: std::fmt::Arguments<'_>) {
        self.counters
            .shm
            .refused_batches
            .fetch_add(1, Ordering::Relaxed);
        self.warn(format_args!("refused a frame: {why}"));
    }

    fn warn(&mut self, what: std::fmt::Arguments<'_>) {
        if self.last_warning.is_none_or(|t| t.elapsed() >= WARN_EVERY) {
            self.last_warning = Some(Instant::now());
            tracing::warn!(
                refused_frames = self.counters.shm.refused_batches.load(Ordering::Relaxed),
                "shared memory ({}): {what}",
                self.subscriber.service()
            );
        }
    }
}

/// Publishes the current version, then every newer one, until training ends or the learner stops.
fn publish_policies(
    publisher: PolicyPublisher,
    mut policy: PolicyWatch,
    mut stopping: watch::Receiver<bool>,
    runtime: tokio::runtime::Handle,
) {
    let mut published = 0u64;
    loop {
        let weights = policy.borrow_and_update().clone();
        let header = PolicyHeader {
            version: weights.version,
            learner_env_steps: weights.learner_env_steps,
        };
        if let Err(e) = publisher.publish(header, &weights.safetensors) {
            tracing::error!(
                "{:#}; actors on this host keep their last policy",
                anyhow::Error::new(e)
            );
            return;
        }
        published += 1;
        // Until the next version: new subscribers get the current one within a tick.
        let more = loop {
            let next = runtime.block_on(async {
                tokio::select! {
                    changed = policy.changed() => Some(changed.is_ok()),
                    _ = stopping.wait_for(|s| *s) => Some(false),
                    _ = tokio::time::sleep(CONNECT_EVERY) => None,
                }
            });
            match next {
                Some(more) => break more,
                None => {
                    if let Err(e) = publisher.connect_new_subscribers() {
                        tracing::warn!("{:#}", anyhow::Error::new(e));
                    }
                }
            }
        };
        if !more {
            break;
        }
    }
    tracing::info!(
        published,
        "shared-memory policy publication stopped ({})",
        publisher.service()
    );
}
