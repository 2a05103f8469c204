//! The iceoryx2 ports rfcl uses, each configured for what it carries:
//!
//! * **Transitions** (actors → learner): `enable_safe_overflow(false)` and a publisher that
//!   retries until the learner's queue has room (`RetryUntilDelivered`). iceoryx2's default
//!   (safe overflow) silently overwrites the oldest queued samples under load; here a full queue
//!   holds the actor back instead, which is the back-pressure the `sync` UTD mode relies on. The
//!   retry ends only when the publisher's owner stops it ([`TransitionPublisher::stop_flag`]): the
//!   frame is then refused and the caller counts it.
//! * **Policy versions** (learner → actors): safe overflow, a queue of one and a history of one.
//!   Each version is one sample, written once before it is sent and never touched again, so a
//!   reader never sees a torn version; every subscriber maps the same sample (no copy per
//!   subscriber); a slow reader finds only the newest version; a new reader gets the current one
//!   at once from the history.
//!
//! All ports use the thread-safe IPC flavour (ports can move between threads) and an `rfcl_` file
//! prefix in `/dev/shm`, apart from other iceoryx2 users. Nodes never install signal handlers
//! (the processes handle SIGINT/SIGTERM themselves).
//!
//! The two kinds differ only in how their services and ports are configured: creating, opening,
//! framing, sending and receiving are written once, generic over the frame's header
//! ([`FrameHeader`]).
use std::marker::PhantomData;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use iceoryx2::config::Config;
use iceoryx2::node::{NodeCreationFailure, NodeView};
use iceoryx2::port::publisher::{Publisher, PublisherCreateError};
use iceoryx2::port::subscriber::{Subscriber, SubscriberCreateError};
use iceoryx2::port::update_connections::ConnectionFailure;
use iceoryx2::port::{BackpressureAction, BackpressureInfo, LoanError, ReceiveError, SendError};
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use iceoryx2::service::builder::publish_subscribe::{
    Builder as ServiceBuilder, PublishSubscribeCreateError, PublishSubscribeOpenError,
};
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;
use iceoryx2::service::port_factory::publisher::PortFactoryPublisher;
use iceoryx2::service::service_name::ServiceNameError;
use thiserror::Error;

use crate::frame::{
    FrameError, PolicyHeader, TransitionHeader, POLICY_HEADER_BYTES, TRANSITION_HEADER_BYTES,
};
use crate::naming;

/// The IPC flavour every rfcl port uses.
pub type Ipc = ipc_threadsafe::Service;

/// Every rfcl service carries byte slices: a frame ([`crate::frame`]).
type Factory = PortFactory<Ipc, [u8], ()>;
type Services = ServiceBuilder<[u8], (), Ipc>;
type Publishers<'a> = PortFactoryPublisher<'a, Ipc, [u8], ()>;

/// What can go wrong with shared memory: what was being done, on which node or service. The
/// iceoryx2 error is the [`source`](std::error::Error::source), not part of the message, so a
/// report of the chain (`{:#}` of an `anyhow::Error`) names it once.
#[derive(Debug, Error)]
pub enum ShmError {
    #[error("shared memory: invalid iceoryx2 node name '{name}'")]
    NodeName {
        name: String,
        source: SemanticStringError,
    },
    #[error("shared memory: invalid iceoryx2 service name '{name}'")]
    ServiceName {
        name: String,
        source: ServiceNameError,
    },
    #[error("shared memory: creating the iceoryx2 node '{node}'")]
    Node {
        node: String,
        source: NodeCreationFailure,
    },
    #[error("shared memory: creating the iceoryx2 service '{service}'")]
    Create {
        service: String,
        source: PublishSubscribeCreateError,
    },
    #[error(
        "shared memory: cannot open the iceoryx2 service '{service}' (it exists only while the \
         learner that announced it runs, on this host)"
    )]
    Open {
        service: String,
        source: PublishSubscribeOpenError,
    },
    #[error("shared memory: creating a publisher on the iceoryx2 service '{service}'")]
    Publisher {
        service: String,
        source: PublisherCreateError,
    },
    #[error("shared memory: creating a subscriber on the iceoryx2 service '{service}'")]
    Subscriber {
        service: String,
        source: SubscriberCreateError,
    },
    #[error("shared memory: receiving on the iceoryx2 service '{service}'")]
    Receive {
        service: String,
        source: ReceiveError,
    },
    #[error("shared memory: loaning a sample for {what} on the iceoryx2 service '{service}'")]
    Loan {
        what: &'static str,
        service: String,
        source: LoanError,
    },
    #[error("shared memory: sending {what} on the iceoryx2 service '{service}'")]
    Send {
        what: &'static str,
        service: String,
        source: SendError,
    },
    #[error("shared memory: connecting new subscribers to the iceoryx2 service '{service}'")]
    Connect {
        service: String,
        source: ConnectionFailure,
    },
    #[error("shared memory: starting the thread that serves the iceoryx2 service '{service}'")]
    Thread {
        service: String,
        source: std::io::Error,
    },
    #[error("shared memory: a frame on the iceoryx2 service '{service}'")]
    Frame { service: String, source: FrameError },
}

/// The iceoryx2 config of every rfcl process: iceoryx2's defaults (no config file is read, so
/// every process of a run agrees), the `rfcl_` prefix, and no automatic dead-node cleanup (done
/// explicitly, and logged, by [`ShmNode::create`]).
pub fn config() -> Config {
    let mut config = Config::default();
    config.global.prefix = FileName::new(b"rfcl_").expect("a valid file name");
    config.global.node.cleanup_dead_nodes_on_creation = false;
    config
}

/// Dead nodes removed when a node was created.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Cleanup {
    /// Dead nodes of this run (a killed predecessor of this process or of another of the run).
    pub of_run: usize,
    /// Dead nodes of other rfcl runs on this host.
    pub others: usize,
    /// Dead nodes whose resources could not be removed (permissions, another cleaner).
    pub failed: usize,
}

/// One process role's iceoryx2 node.
#[derive(Debug)]
pub struct ShmNode {
    node: Node<Ipc>,
    name: String,
}

impl ShmNode {
    /// Removes the stale files of every dead rfcl node on this host (those of `run_name` are
    /// counted apart), then creates the node `rfcl/<run_name>/<role>`.
    pub fn create(run_name: &str, role: &str) -> Result<(Self, Cleanup), ShmError> {
        // iceoryx2's own log goes to stderr; warnings and worse only, unless IOX2_LOG_LEVEL says.
        set_log_level_from_env_or(LogLevel::Warn);
        let name = naming::node_name(run_name, role);
        let config = config();
        let cleanup = cleanup_dead_nodes(&config, &naming::node_prefix(run_name));
        let node_name = NodeName::new(&name).map_err(|source| ShmError::NodeName {
            name: name.clone(),
            source,
        })?;
        let node = NodeBuilder::new()
            .name(&node_name)
            .config(&config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Ipc>()
            .map_err(|source| ShmError::Node {
                node: name.clone(),
                source,
            })?;
        Ok((Self { node, name }, cleanup))
    }

    pub fn name(&self) -> &str {
        &self.name
    }
}

fn cleanup_dead_nodes(config: &Config, run_prefix: &str) -> Cleanup {
    let mut dead = Vec::new();
    let listed = Node::<Ipc>::list(config, |state| {
        if let NodeState::Dead(view) = state {
            let name = view
                .details()
                .as_ref()
                .map(|d| d.name().as_str().to_string())
                .unwrap_or_default();
            dead.push((name, view));
        }
        CallbackProgression::Continue
    });
    if let Err(e) = listed {
        tracing::warn!(
            "shared memory: listing iceoryx2 nodes failed ({e:?}); no stale-node cleanup"
        );
    }
    let mut cleanup = Cleanup::default();
    for (name, view) in dead {
        match view.blocking_remove_stale_resources(Duration::from_secs(1)) {
            Ok(()) if name.starts_with(run_prefix) => cleanup.of_run += 1,
            Ok(()) => cleanup.others += 1,
            Err(e) => {
                cleanup.failed += 1;
                tracing::warn!("shared memory: removing the dead node '{name}' failed: {e:?}");
            }
        }
    }
    cleanup
}

/// The kinds of frame a port carries: a header of a fixed size before the body.
pub trait FrameHeader: Copy + sealed::Sealed {
    /// Bytes before the body.
    const BYTES: usize;
    /// The frame in errors, e.g. "a transition frame".
    const WHAT: &'static str;
    fn encode(&self, out: &mut [u8]);
    fn decode(frame: &[u8]) -> Result<(Self, &[u8]), FrameError>;
}

mod sealed {
    pub trait Sealed {}
}

/// [`FrameHeader`] for a header of [`crate::frame`] (its inherent `encode` and `decode`).
macro_rules! frame_header {
    ($header:ty, $bytes:expr, $what:literal) => {
        impl sealed::Sealed for $header {}

        impl FrameHeader for $header {
            const BYTES: usize = $bytes;
            const WHAT: &'static str = $what;
            fn encode(&self, out: &mut [u8]) {
                <$header>::encode(self, out)
            }
            fn decode(frame: &[u8]) -> Result<(Self, &[u8]), FrameError> {
                <$header>::decode(frame)
            }
        }
    };
}

frame_header!(
    TransitionHeader,
    TRANSITION_HEADER_BYTES,
    "a transition frame"
);
frame_header!(PolicyHeader, POLICY_HEADER_BYTES, "a policy version");

/// A received frame, still in shared memory; dropping it hands the memory back to its publisher.
pub struct Frame<H> {
    sample: Sample<Ipc, [u8], ()>,
    kind: PhantomData<fn() -> H>,
}

impl<H: FrameHeader> Frame<H> {
    /// The header and the body (the records, or the policy's safetensors).
    pub fn decode(&self) -> Result<(H, &[u8]), FrameError> {
        H::decode(self.sample.payload())
    }
}

/// A received transition frame: the header and the records in rfcl-core's layout.
pub type TransitionFrame = Frame<TransitionHeader>;
/// A received policy version: the header and the safetensors bytes.
pub type PolicyFrame = Frame<PolicyHeader>;

/// The `[u8]` publish-subscribe service `service`, created on `node` as `configure` sets it up.
fn create_service(
    node: &ShmNode,
    service: &str,
    configure: impl FnOnce(Services) -> Services,
) -> Result<Factory, ShmError> {
    configure(service_builder(node, service)?)
        .create()
        .map_err(|source| ShmError::Create {
            service: service.to_string(),
            source,
        })
}

/// The `[u8]` publish-subscribe service `service`, opened on `node`; it must overflow safely or
/// not as `safe_overflow` says.
fn open_service(node: &ShmNode, service: &str, safe_overflow: bool) -> Result<Factory, ShmError> {
    service_builder(node, service)?
        .enable_safe_overflow(safe_overflow)
        .open()
        .map_err(|source| ShmError::Open {
            service: service.to_string(),
            source,
        })
}

fn service_builder(node: &ShmNode, service: &str) -> Result<Services, ShmError> {
    let name = ServiceName::new(service).map_err(|source| ShmError::ServiceName {
        name: service.to_string(),
        source,
    })?;
    Ok(node.node.service_builder(&name).publish_subscribe::<[u8]>())
}

/// One end of a service: its iceoryx2 port `P` (a publisher or a subscriber) for frames with
/// headers `H`, the service's name, and the node that holds both (dropped last).
struct End<P, H> {
    port: P,
    service: String,
    kind: PhantomData<fn() -> H>,
    _node: ShmNode,
}

impl<P, H> End<P, H> {
    fn new(node: ShmNode, service: &str, port: P) -> Self {
        Self {
            port,
            service: service.to_string(),
            kind: PhantomData,
            _node: node,
        }
    }
}

impl<P, H> std::fmt::Debug for End<P, H> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("End")
            .field("service", &self.service)
            .finish()
    }
}

/// The receiving end of a service.
type Receiver<H> = End<Subscriber<Ipc, [u8], ()>, H>;
/// The sending end of a service.
type Sender<H> = End<Publisher<Ipc, [u8], ()>, H>;

impl<H: FrameHeader> Receiver<H> {
    /// A subscriber on `factory` (the service `service`) queueing up to `buffer` frames.
    fn subscribe(
        node: ShmNode,
        service: &str,
        factory: &Factory,
        buffer: usize,
    ) -> Result<Self, ShmError> {
        let subscriber = factory
            .subscriber_builder()
            .buffer_size(buffer)
            .create()
            .map_err(|source| ShmError::Subscriber {
                service: service.to_string(),
                source,
            })?;
        Ok(Self::new(node, service, subscriber))
    }

    /// The next queued frame, if one is there (never blocks).
    fn receive(&self) -> Result<Option<Frame<H>>, ShmError> {
        self.port
            .receive()
            .map(|s| {
                s.map(|sample| Frame {
                    sample,
                    kind: PhantomData,
                })
            })
            .map_err(|source| ShmError::Receive {
                service: self.service.clone(),
                source,
            })
    }
}

impl<H: FrameHeader> Sender<H> {
    /// A publisher on `factory` (the service `service`) that loans one sample at a time, sized
    /// for bodies of `body_bytes` (bigger ones still work: the memory grows), set up further by
    /// `configure`.
    fn publish(
        node: ShmNode,
        service: &str,
        factory: &Factory,
        body_bytes: usize,
        configure: impl FnOnce(Publishers<'_>) -> Publishers<'_>,
    ) -> Result<Self, ShmError> {
        let builder = factory
            .publisher_builder()
            .initial_max_slice_len(H::BYTES + body_bytes)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(1);
        let publisher = configure(builder)
            .create()
            .map_err(|source| ShmError::Publisher {
                service: service.to_string(),
                source,
            })?;
        Ok(Self::new(node, service, publisher))
    }

    /// Writes `header` and `body` into a fresh sample and sends it; the subscribers it reached.
    fn send(&self, header: &H, body: &[u8]) -> Result<usize, ShmError> {
        let mut sample = self
            .port
            .loan_slice(H::BYTES + body.len())
            .map_err(|source| ShmError::Loan {
                what: H::WHAT,
                service: self.service.clone(),
                source,
            })?;
        let payload = sample.payload_mut();
        header.encode(payload);
        payload[H::BYTES..].copy_from_slice(body);
        sample.send().map_err(|source| ShmError::Send {
            what: H::WHAT,
            service: self.service.clone(),
            source,
        })
    }
}

/// Limits of a run's transition service, fixed by the learner when it creates the service.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TransitionLimits {
    /// Actor processes that can publish at once.
    pub max_publishers: usize,
    /// Frames queued per publisher before it is held back.
    pub queue_frames: usize,
}

impl Default for TransitionLimits {
    fn default() -> Self {
        Self {
            max_publishers: 32,
            queue_frames: 2,
        }
    }
}

/// The learner's end of the transition service (it creates the service).
#[derive(Debug)]
pub struct TransitionSubscriber {
    port: Receiver<TransitionHeader>,
}

impl TransitionSubscriber {
    pub fn create(
        node: ShmNode,
        service: &str,
        limits: TransitionLimits,
    ) -> Result<Self, ShmError> {
        let queue = limits.queue_frames.max(1);
        let publishers = limits.max_publishers.max(1);
        let factory = create_service(&node, service, |b| {
            b.enable_safe_overflow(false)
                .history_size(0)
                .subscriber_max_buffer_size(queue)
                .subscriber_max_borrowed_samples(2)
                .max_publishers(publishers)
                .max_subscribers(1)
                .max_nodes(publishers + 4)
        })?;
        let port = Receiver::subscribe(node, service, &factory, queue)?;
        Ok(Self { port })
    }

    /// The next queued frame of any publisher, if one is there (never blocks).
    pub fn receive(&self) -> Result<Option<TransitionFrame>, ShmError> {
        self.port.receive()
    }

    pub fn service(&self) -> &str {
        &self.port.service
    }
}

/// What became of a frame handed to [`TransitionPublisher::send`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sent {
    /// In the learner's queue.
    Delivered,
    /// No learner received it: it stopped or died, or (right at the start) its subscriber has
    /// not connected yet while the queue is full. Nothing was delivered: send it again.
    NoSubscriber,
}

/// An actor's end of the transition service (the learner must have created it).
#[derive(Debug)]
pub struct TransitionPublisher {
    port: Sender<TransitionHeader>,
    header: TransitionHeader,
    stop: Arc<AtomicBool>,
}

impl TransitionPublisher {
    /// Opens the service and creates a publisher sized for frames of up to `max_records` records
    /// of `record_bytes` each (bigger frames still work: the memory grows).
    pub fn open(
        node: ShmNode,
        service: &str,
        max_records: usize,
        record_bytes: usize,
    ) -> Result<Self, ShmError> {
        // Refuses a service that would overwrite queued transitions.
        let factory = open_service(&node, service, false)?;
        let stop = Arc::new(AtomicBool::new(false));
        let stop_in_handler = stop.clone();
        let port = Sender::publish(
            node,
            service,
            &factory,
            max_records.max(1) * record_bytes,
            |b| {
                b.backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
                    // Retry (iceoryx2 waits adaptively between tries) until the owner says stop.
                    .set_backpressure_handler(move |_: &BackpressureInfo| {
                        if stop_in_handler.load(Ordering::Relaxed) {
                            BackpressureAction::DiscardDataAndFail
                        } else {
                            BackpressureAction::Retry
                        }
                    })
            },
        )?;
        Ok(Self {
            port,
            header: TransitionHeader {
                publisher: random_u64(),
                ..TransitionHeader::default()
            },
            stop,
        })
    }

    /// Set it (from any thread) to end a `send` that waits for room: that frame is then refused.
    pub fn stop_flag(&self) -> Arc<AtomicBool> {
        self.stop.clone()
    }

    /// Frames this publisher has delivered.
    pub fn frames_sent(&self) -> u64 {
        self.header.seq
    }

    /// Sends `count` records (`records`, rfcl-core's layout) as one frame. Blocks while the
    /// learner's queue is full (back-pressure), until the stop flag is set (an error: the frame is
    /// not delivered).
    pub fn send(
        &mut self,
        actor_id: u32,
        obs_dim: u32,
        action_dim: u32,
        count: u32,
        records: &[u8],
    ) -> Result<Sent, ShmError> {
        let header = TransitionHeader {
            actor_id,
            obs_dim,
            action_dim,
            count,
            ..self.header
        };
        if self.port.send(&header, records)? == 0 {
            return Ok(Sent::NoSubscriber);
        }
        self.header.seq += 1;
        self.header.records_before += u64::from(count);
        Ok(Sent::Delivered)
    }

    pub fn service(&self) -> &str {
        &self.port.service
    }
}

/// Limits of a run's policy service.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PolicyLimits {
    /// Actor processes that can subscribe at once.
    pub max_subscribers: usize,
}

impl Default for PolicyLimits {
    fn default() -> Self {
        Self {
            max_subscribers: 32,
        }
    }
}

/// The learner's end of the policy service (it creates the service).
#[derive(Debug)]
pub struct PolicyPublisher {
    port: Sender<PolicyHeader>,
}

impl PolicyPublisher {
    /// Creates the service, sized for policies of about `weights_bytes` (bigger ones still work).
    pub fn create(
        node: ShmNode,
        service: &str,
        limits: PolicyLimits,
        weights_bytes: usize,
    ) -> Result<Self, ShmError> {
        let subscribers = limits.max_subscribers.max(1);
        let factory = create_service(&node, service, |b| {
            b.enable_safe_overflow(true)
                .history_size(1)
                .subscriber_max_buffer_size(1)
                .subscriber_max_borrowed_samples(1)
                .max_publishers(1)
                .max_subscribers(subscribers)
                .max_nodes(subscribers + 4)
        })?;
        let port = Sender::publish(node, service, &factory, weights_bytes, |b| b)?;
        Ok(Self { port })
    }

    /// Publishes one whole version: written into a fresh sample, then sent; never written again.
    pub fn publish(&self, header: PolicyHeader, safetensors: &[u8]) -> Result<(), ShmError> {
        self.port.send(&header, safetensors).map(|_| ())
    }

    /// Connects subscribers that arrived since the last call and hands them the current version
    /// (the history). Publishing does this too; call it while no new version comes, or a new
    /// actor waits for the next one.
    pub fn connect_new_subscribers(&self) -> Result<(), ShmError> {
        use iceoryx2::port::update_connections::UpdateConnections;
        self.port
            .port
            .update_connections()
            .map_err(|source| ShmError::Connect {
                service: self.port.service.clone(),
                source,
            })
    }

    pub fn service(&self) -> &str {
        &self.port.service
    }
}

/// An actor's end of the policy service.
#[derive(Debug)]
pub struct PolicySubscriber {
    port: Receiver<PolicyHeader>,
}

impl PolicySubscriber {
    /// Opens the learner's policy service; the current version is then the first one received.
    pub fn open(node: ShmNode, service: &str) -> Result<Self, ShmError> {
        let factory = open_service(&node, service, true)?;
        let port = Receiver::subscribe(node, service, &factory, 1)?;
        Ok(Self { port })
    }

    /// The newest version published since the last call, if any. The queue holds one version
    /// and a newer one replaces an unread older one, so one receive is the newest.
    pub fn latest(&self) -> Result<Option<PolicyFrame>, ShmError> {
        self.port.receive()
    }

    pub fn service(&self) -> &str {
        &self.port.service
    }
}

fn random_u64() -> u64 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    h.finish()
}

#[cfg(test)]
mod tests {
    use std::error::Error as _;

    use super::*;

    #[test]
    fn an_error_names_the_service_and_carries_the_iceoryx2_cause_once() {
        let run = format!("shm-unit-{}", naming::new_run_id());
        let names = naming::ServiceNames::new(&run, &naming::new_run_id());
        let (node, _) = ShmNode::create(&run, "nobody").unwrap();
        let e = PolicySubscriber::open(node, &names.policy).unwrap_err();
        let message = e.to_string();
        assert!(message.contains(&names.policy), "{message}");
        let source = e
            .source()
            .expect("the iceoryx2 error is the source")
            .to_string();
        assert!(source.contains("PublishSubscribeOpenError"), "{source}");
        assert!(
            !message.contains(&source),
            "the cause is in the message too: {message}"
        );
    }
}
