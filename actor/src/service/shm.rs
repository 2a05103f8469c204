//! The actor's transport choice and its shared-memory side (docs/DESIGN.md, "Processes": same-host
//! actors use iceoryx2, remote ones gRPC; one code path decides).
//!
//! [`decide`] is that code path. `--transport auto` (the default) uses shared memory when the
//! learner serves it, its host identity (machine id, boot id, `/dev/shm` device:
//! `rfcl_shm::host_identity`) equals the actor's, and both services open; otherwise gRPC, with
//! the reason logged. `--transport shm` insists (a service that does not open is an error naming
//! it); `--transport grpc` never tries.
//!
//! Over shared memory, a dedicated thread publishes the transition batches (blocking while the
//! learner's queue is full: the learner's back-pressure reaches the env loop through the small
//! batch channel, as with gRPC) and another follows the policy service into the same `watch`
//! channel the gRPC WatchPolicy task feeds, so the env and eval loops do not know which transport
//! runs.
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use rfcl_proto::v1;
use rfcl_shm::{PolicySubscriber, Sent, ShmNode, TransitionPublisher};
use tokio::sync::{mpsc, oneshot, watch};

use super::links::{backoff, PushCounters};

/// `--transport`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Choice {
    /// Shared memory when on the learner's host and its services open, else gRPC.
    Auto,
    /// Shared memory, or fail.
    Shm,
    /// gRPC only.
    Grpc,
}

/// What [`decide`] found before trying to open anything.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Plan {
    /// Try shared memory; `required` makes a failure to open an error.
    Shm { required: bool },
    /// gRPC, and why.
    Grpc { why: String },
}

/// The transport choice from `--transport`, the learner's run description and this host's
/// identity.
pub fn decide(choice: Choice, info: &v1::RunInfo, own_host: &str) -> Result<Plan> {
    let served = !info.shm_transitions_service.is_empty() && !info.shm_policy_service.is_empty();
    match choice {
        Choice::Grpc => Ok(Plan::Grpc {
            why: "--transport grpc".into(),
        }),
        Choice::Shm if !served => bail!(
            "--transport shm: the learner serves no shared-memory services (it runs with --no-shm, \
             or predates them); use --transport auto or grpc"
        ),
        Choice::Shm => Ok(Plan::Shm { required: true }),
        Choice::Auto if !served => Ok(Plan::Grpc {
            why: "the learner serves no shared-memory services".into(),
        }),
        Choice::Auto if info.learner_host_identity != own_host => Ok(Plan::Grpc {
            why: format!(
                "the learner is on another host ({}; this host: {own_host})",
                info.learner_host_identity
            ),
        }),
        Choice::Auto => Ok(Plan::Shm { required: false }),
    }
}

/// Both shared-memory ports of an actor, opened.
pub struct ShmLink {
    publisher: TransitionPublisher,
    policy: PolicySubscriber,
}

impl ShmLink {
    /// Opens the learner's transition and policy services (cleaning up dead nodes of the run
    /// first). Sized for batches of `batch` records of `record_bytes`.
    pub fn open(
        info: &v1::RunInfo,
        actor_id: u32,
        batch: usize,
        record_bytes: usize,
    ) -> Result<Self> {
        let (node, cleanup) =
            ShmNode::create(&info.run_name, &format!("actor-{actor_id}-transitions"))?;
        if cleanup.of_run + cleanup.others > 0 {
            tracing::info!(
                of_this_run = cleanup.of_run,
                of_other_runs = cleanup.others,
                "shared memory: removed the stale files of dead iceoryx2 nodes"
            );
        }
        let publisher =
            TransitionPublisher::open(node, &info.shm_transitions_service, batch, record_bytes)?;
        let (node, _) = ShmNode::create(&info.run_name, &format!("actor-{actor_id}-policy"))?;
        let policy = PolicySubscriber::open(node, &info.shm_policy_service)?;
        Ok(Self { publisher, policy })
    }

    pub fn services(&self) -> (String, String) {
        (
            self.publisher.service().to_string(),
            self.policy.service().to_string(),
        )
    }

    pub fn into_parts(self) -> (TransitionPublisher, PolicySubscriber) {
        (self.publisher, self.policy)
    }
}

/// Starts the policy thread: it feeds `latest` with each newer version until `stop` is set or
/// nobody listens.
pub fn start_policy_follower(
    policy: PolicySubscriber,
    latest: watch::Sender<Option<Arc<v1::PolicyWeights>>>,
    stop: Arc<AtomicBool>,
) -> Result<()> {
    std::thread::Builder::new()
        .name("shm-policy".into())
        .spawn(move || follow_policy(policy, latest, stop))
        .context("starting the shared-memory policy thread")?;
    Ok(())
}

/// How often the policy thread looks for a new version when there was none.
const POLICY_POLL: Duration = Duration::from_millis(2);

fn follow_policy(
    policy: PolicySubscriber,
    latest: watch::Sender<Option<Arc<v1::PolicyWeights>>>,
    stop: Arc<AtomicBool>,
) {
    let mut last = 0u64;
    while !stop.load(Ordering::Relaxed) && !latest.is_closed() {
        let frame = match policy.latest() {
            Ok(Some(frame)) => frame,
            Ok(None) => {
                std::thread::sleep(POLICY_POLL);
                continue;
            }
            Err(e) => {
                tracing::warn!("{:#}", anyhow!(e));
                std::thread::sleep(Duration::from_millis(100));
                continue;
            }
        };
        let (header, weights) = match frame.decode() {
            Ok(decoded) => decoded,
            Err(e) => {
                tracing::warn!("shared memory ({}): {e}", policy.service());
                continue;
            }
        };
        if header.version <= last {
            continue;
        }
        last = header.version;
        tracing::debug!(version = header.version, "new policy (shared memory)");
        // One copy out of shared memory per actor process (the learner made none per subscriber);
        // the sample is handed back right after.
        latest.send_replace(Some(Arc::new(v1::PolicyWeights {
            version: header.version,
            safetensors: weights.to_vec().into(),
            learner_env_steps: header.learner_env_steps,
        })));
    }
}

/// The transition thread: publishes every batch from `batches` until it closes. A frame nobody
/// receives (the learner stopped subscribing) is retried with backoff for `retry_for`, then the
/// actor fails; setting `stop` ends a send that waits for room (the frame is counted as given up).
pub fn start_pusher(
    mut publisher: TransitionPublisher,
    mut batches: mpsc::Receiver<v1::TransitionBatch>,
    counters: Arc<PushCounters>,
    retry_for: Duration,
) -> Result<(oneshot::Receiver<Result<()>>, Arc<AtomicBool>)> {
    let stop = publisher.stop_flag();
    let (done_tx, done_rx) = oneshot::channel();
    std::thread::Builder::new()
        .name("shm-transitions".into())
        .spawn(move || {
            let result = (|| {
                while let Some(batch) = batches.blocking_recv() {
                    send_one(&mut publisher, &batch, &counters, retry_for)?;
                }
                Ok(())
            })();
            let _ = done_tx.send(result);
        })
        .context("starting the shared-memory transition thread")?;
    Ok((done_rx, stop))
}

fn send_one(
    publisher: &mut TransitionPublisher,
    batch: &v1::TransitionBatch,
    counters: &PushCounters,
    retry_for: Duration,
) -> Result<()> {
    let count = u64::from(batch.count);
    let mut backoff = backoff(retry_for);
    loop {
        let sent = publisher.send(
            batch.actor_id,
            batch.obs_dim,
            batch.action_dim,
            batch.count,
            &batch.records,
        );
        match sent {
            Ok(Sent::Delivered) => {
                counters.sent.fetch_add(count, Ordering::Relaxed);
                if backoff.attempts() > 2 {
                    tracing::info!("shared memory: the learner receives again");
                }
                return Ok(());
            }
            Ok(Sent::NoSubscriber) => {
                let Some(delay) = backoff.next_delay(Instant::now()) else {
                    counters.given_up.fetch_add(count, Ordering::Relaxed);
                    bail!(
                        "no learner has received on the shared-memory service '{}' for {:.0} s",
                        publisher.service(),
                        retry_for.as_secs_f64()
                    );
                };
                // Right at the start this is the learner's subscriber connecting: say so only
                // when it lasts.
                if backoff.attempts() > 2 {
                    tracing::warn!(
                        "shared memory: no learner receives on '{}'; retrying in {} ms",
                        publisher.service(),
                        delay.as_millis()
                    );
                }
                std::thread::sleep(delay);
            }
            Err(e) => {
                counters.given_up.fetch_add(count, Ordering::Relaxed);
                return Err(anyhow!(e).context(format!("{count} transitions given up")));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info(served: bool, host: &str) -> v1::RunInfo {
        v1::RunInfo {
            shm_transitions_service: if served {
                "rfcl/r/1/transitions".into()
            } else {
                String::new()
            },
            shm_policy_service: if served {
                "rfcl/r/1/policy".into()
            } else {
                String::new()
            },
            learner_host_identity: host.into(),
            ..Default::default()
        }
    }

    #[test]
    fn auto_takes_shared_memory_only_on_the_learners_host() {
        assert_eq!(
            decide(Choice::Auto, &info(true, "h1"), "h1").unwrap(),
            Plan::Shm { required: false }
        );
        let Plan::Grpc { why } = decide(Choice::Auto, &info(true, "h1"), "h2").unwrap() else {
            panic!("another host must use gRPC");
        };
        assert!(why.contains("another host"), "{why}");
        let Plan::Grpc { why } = decide(Choice::Auto, &info(false, "h1"), "h1").unwrap() else {
            panic!("no services, no shared memory");
        };
        assert!(why.contains("no shared-memory services"), "{why}");
    }

    #[test]
    fn forced_choices_are_obeyed_or_refused_clearly() {
        assert_eq!(
            decide(Choice::Shm, &info(true, "h1"), "h2").unwrap(),
            Plan::Shm { required: true }
        );
        let e = decide(Choice::Shm, &info(false, "h1"), "h1").unwrap_err();
        assert!(e.to_string().contains("--no-shm"), "{e}");
        assert!(matches!(
            decide(Choice::Grpc, &info(true, "h1"), "h1").unwrap(),
            Plan::Grpc { .. }
        ));
    }
}
