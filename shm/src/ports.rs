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
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use iceoryx2::config::Config;
use iceoryx2::node::NodeView;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::{BackpressureAction, BackpressureInfo};
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use thiserror::Error;

use crate::frame::{
    FrameError, PolicyHeader, TransitionHeader, POLICY_HEADER_BYTES, TRANSITION_HEADER_BYTES,
};
use crate::naming;

/// The IPC flavour every rfcl port uses.
pub type Ipc = ipc_threadsafe::Service;

/// What can go wrong with shared memory; every variant names the node or service.
#[derive(Debug, Error)]
pub enum ShmError {
    #[error("shared memory: invalid iceoryx2 name '{name}': {problem}")]
    Name { name: String, problem: String },
    #[error("shared memory: creating the iceoryx2 node '{node}': {problem}")]
    Node { node: String, problem: String },
    #[error("shared memory: creating the iceoryx2 service '{service}': {problem}")]
    Create { service: String, problem: String },
    #[error(
        "shared memory: cannot open the iceoryx2 service '{service}': {problem} (it exists only \
         while the learner that announced it runs, on this host)"
    )]
    Open { service: String, problem: String },
    #[error("shared memory: creating a {port} on the iceoryx2 service '{service}': {problem}")]
    Port {
        port: &'static str,
        service: String,
        problem: String,
    },
    #[error("shared memory: {what} on the iceoryx2 service '{service}': {problem}")]
    Io {
        what: &'static str,
        service: String,
        problem: String,
    },
    #[error("shared memory: a frame on the iceoryx2 service '{service}': {error}")]
    Frame { service: String, error: FrameError },
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
        let node_name = NodeName::new(&name).map_err(|e| ShmError::Name {
            name: name.clone(),
            problem: format!("{e:?}"),
        })?;
        let node = NodeBuilder::new()
            .name(&node_name)
            .config(&config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Ipc>()
            .map_err(|e| ShmError::Node {
                node: name.clone(),
                problem: e.to_string(),
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

fn service_name(name: &str) -> Result<ServiceName, ShmError> {
    ServiceName::new(name).map_err(|e| ShmError::Name {
        name: name.to_string(),
        problem: format!("{e:?}"),
    })
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
    subscriber: Subscriber<Ipc, [u8], ()>,
    service: String,
    _node: ShmNode,
}

/// A received transition frame; dropping it hands the memory back to its publisher.
pub struct TransitionFrame {
    sample: Sample<Ipc, [u8], ()>,
}

impl TransitionFrame {
    /// The header and the records (still in shared memory).
    pub fn decode(&self) -> Result<(TransitionHeader, &[u8]), FrameError> {
        TransitionHeader::decode(self.sample.payload())
    }
}

impl TransitionSubscriber {
    pub fn create(
        node: ShmNode,
        service: &str,
        limits: TransitionLimits,
    ) -> Result<Self, ShmError> {
        let create = |problem: String| ShmError::Create {
            service: service.to_string(),
            problem,
        };
        let factory = node
            .node
            .service_builder(&service_name(service)?)
            .publish_subscribe::<[u8]>()
            .enable_safe_overflow(false)
            .history_size(0)
            .subscriber_max_buffer_size(limits.queue_frames.max(1))
            .subscriber_max_borrowed_samples(2)
            .max_publishers(limits.max_publishers.max(1))
            .max_subscribers(1)
            .max_nodes(limits.max_publishers.max(1) + 4)
            .create()
            .map_err(|e| create(e.to_string()))?;
        let subscriber = factory
            .subscriber_builder()
            .buffer_size(limits.queue_frames.max(1))
            .create()
            .map_err(|e| ShmError::Port {
                port: "subscriber",
                service: service.to_string(),
                problem: e.to_string(),
            })?;
        Ok(Self {
            subscriber,
            service: service.to_string(),
            _node: node,
        })
    }

    /// The next queued frame of any publisher, if one is there (never blocks).
    pub fn receive(&self) -> Result<Option<TransitionFrame>, ShmError> {
        self.subscriber
            .receive()
            .map(|s| s.map(|sample| TransitionFrame { sample }))
            .map_err(|e| ShmError::Io {
                what: "receiving",
                service: self.service.clone(),
                problem: format!("{e:?}"),
            })
    }

    pub fn service(&self) -> &str {
        &self.service
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
pub struct TransitionPublisher {
    publisher: Publisher<Ipc, [u8], ()>,
    service: String,
    header: TransitionHeader,
    stop: Arc<AtomicBool>,
    _node: ShmNode,
}

impl std::fmt::Debug for TransitionPublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TransitionPublisher")
            .field("service", &self.service)
            .field("header", &self.header)
            .finish()
    }
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
        let factory = node
            .node
            .service_builder(&service_name(service)?)
            .publish_subscribe::<[u8]>()
            // Refuses a service that would overwrite queued transitions.
            .enable_safe_overflow(false)
            .open()
            .map_err(|e| ShmError::Open {
                service: service.to_string(),
                problem: e.to_string(),
            })?;
        let stop = Arc::new(AtomicBool::new(false));
        let stop_in_handler = stop.clone();
        let publisher = factory
            .publisher_builder()
            .initial_max_slice_len(TRANSITION_HEADER_BYTES + max_records.max(1) * record_bytes)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(1)
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            // Retry (iceoryx2 waits adaptively between tries) until the owner says stop.
            .set_backpressure_handler(move |_: &BackpressureInfo| {
                if stop_in_handler.load(Ordering::Relaxed) {
                    BackpressureAction::DiscardDataAndFail
                } else {
                    BackpressureAction::Retry
                }
            })
            .create()
            .map_err(|e| ShmError::Port {
                port: "publisher",
                service: service.to_string(),
                problem: e.to_string(),
            })?;
        Ok(Self {
            publisher,
            service: service.to_string(),
            header: TransitionHeader {
                publisher: random_u64(),
                ..TransitionHeader::default()
            },
            stop,
            _node: node,
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
        let io = |what: &'static str, problem: String| ShmError::Io {
            what,
            service: self.service.clone(),
            problem,
        };
        let header = TransitionHeader {
            actor_id,
            obs_dim,
            action_dim,
            count,
            ..self.header
        };
        let len = TRANSITION_HEADER_BYTES + records.len();
        let mut sample = self
            .publisher
            .loan_slice(len)
            .map_err(|e| io("loaning a sample", format!("{e:?}")))?;
        let payload = sample.payload_mut();
        header.encode(payload);
        payload[TRANSITION_HEADER_BYTES..].copy_from_slice(records);
        let receivers = sample
            .send()
            .map_err(|e| io("sending a transition frame", format!("{e:?}")))?;
        if receivers == 0 {
            return Ok(Sent::NoSubscriber);
        }
        self.header.seq += 1;
        self.header.records_before += u64::from(count);
        Ok(Sent::Delivered)
    }

    pub fn service(&self) -> &str {
        &self.service
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
pub struct PolicyPublisher {
    publisher: Publisher<Ipc, [u8], ()>,
    service: String,
    _node: ShmNode,
}

impl std::fmt::Debug for PolicyPublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PolicyPublisher")
            .field("service", &self.service)
            .finish()
    }
}

impl PolicyPublisher {
    /// Creates the service, sized for policies of about `weights_bytes` (bigger ones still work).
    pub fn create(
        node: ShmNode,
        service: &str,
        limits: PolicyLimits,
        weights_bytes: usize,
    ) -> Result<Self, ShmError> {
        let factory = node
            .node
            .service_builder(&service_name(service)?)
            .publish_subscribe::<[u8]>()
            .enable_safe_overflow(true)
            .history_size(1)
            .subscriber_max_buffer_size(1)
            .subscriber_max_borrowed_samples(1)
            .max_publishers(1)
            .max_subscribers(limits.max_subscribers.max(1))
            .max_nodes(limits.max_subscribers.max(1) + 4)
            .create()
            .map_err(|e| ShmError::Create {
                service: service.to_string(),
                problem: e.to_string(),
            })?;
        let publisher = factory
            .publisher_builder()
            .initial_max_slice_len(POLICY_HEADER_BYTES + weights_bytes)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(1)
            .create()
            .map_err(|e| ShmError::Port {
                port: "publisher",
                service: service.to_string(),
                problem: e.to_string(),
            })?;
        Ok(Self {
            publisher,
            service: service.to_string(),
            _node: node,
        })
    }

    /// Publishes one whole version: written into a fresh sample, then sent; never written again.
    pub fn publish(&self, header: PolicyHeader, safetensors: &[u8]) -> Result<(), ShmError> {
        let io = |what: &'static str, problem: String| ShmError::Io {
            what,
            service: self.service.clone(),
            problem,
        };
        let mut sample = self
            .publisher
            .loan_slice(POLICY_HEADER_BYTES + safetensors.len())
            .map_err(|e| io("loaning a sample", format!("{e:?}")))?;
        let payload = sample.payload_mut();
        header.encode(payload);
        payload[POLICY_HEADER_BYTES..].copy_from_slice(safetensors);
        sample
            .send()
            .map_err(|e| io("publishing a policy version", format!("{e:?}")))?;
        Ok(())
    }

    /// Connects subscribers that arrived since the last call and hands them the current version
    /// (the history). Publishing does this too; call it while no new version comes, or a new
    /// actor waits for the next one.
    pub fn connect_new_subscribers(&self) -> Result<(), ShmError> {
        use iceoryx2::port::update_connections::UpdateConnections;
        self.publisher
            .update_connections()
            .map_err(|e| ShmError::Io {
                what: "connecting new subscribers",
                service: self.service.clone(),
                problem: format!("{e:?}"),
            })
    }

    pub fn service(&self) -> &str {
        &self.service
    }
}

/// An actor's end of the policy service.
pub struct PolicySubscriber {
    subscriber: Subscriber<Ipc, [u8], ()>,
    service: String,
    _node: ShmNode,
}

impl std::fmt::Debug for PolicySubscriber {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PolicySubscriber")
            .field("service", &self.service)
            .finish()
    }
}

/// A received policy version, still in shared memory.
pub struct PolicyFrame {
    sample: Sample<Ipc, [u8], ()>,
}

impl PolicyFrame {
    /// The version's header and its safetensors bytes.
    pub fn decode(&self) -> Result<(PolicyHeader, &[u8]), FrameError> {
        PolicyHeader::decode(self.sample.payload())
    }
}

impl PolicySubscriber {
    /// Opens the learner's policy service; the current version is then the first one received.
    pub fn open(node: ShmNode, service: &str) -> Result<Self, ShmError> {
        let factory = node
            .node
            .service_builder(&service_name(service)?)
            .publish_subscribe::<[u8]>()
            .enable_safe_overflow(true)
            .open()
            .map_err(|e| ShmError::Open {
                service: service.to_string(),
                problem: e.to_string(),
            })?;
        let subscriber = factory
            .subscriber_builder()
            .buffer_size(1)
            .create()
            .map_err(|e| ShmError::Port {
                port: "subscriber",
                service: service.to_string(),
                problem: e.to_string(),
            })?;
        Ok(Self {
            subscriber,
            service: service.to_string(),
            _node: node,
        })
    }

    /// The newest version published since the last call, if any. The queue holds one version
    /// and a newer one replaces an unread older one, so one receive is the newest.
    pub fn latest(&self) -> Result<Option<PolicyFrame>, ShmError> {
        self.subscriber
            .receive()
            .map(|s| s.map(|sample| PolicyFrame { sample }))
            .map_err(|e| ShmError::Io {
                what: "receiving",
                service: self.service.clone(),
                problem: format!("{e:?}"),
            })
    }

    pub fn service(&self) -> &str {
        &self.service
    }
}

fn random_u64() -> u64 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    h.finish()
}
