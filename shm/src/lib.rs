//! rfcl's same-host transport: transition batches (actors → learner) and policy versions
//! (learner → actors) over iceoryx2 shared memory (docs/DESIGN.md, "The path of a transition").
//!
//! * [`frame`]: the bytes of a sample (a small header, then the records in rfcl-core's
//!   `RecordLayout`, or the policy's safetensors), pure and tested;
//! * [`naming`]: service names per run and learner session, node names per run, the host identity
//!   an actor compares to choose this transport;
//! * [`ports`]: the configured iceoryx2 ports (no sample is ever lost silently: transitions use
//!   back-pressure, policies keep only the newest whole version), and the dead-node cleanup each
//!   process runs at start.
//!
//! No `unsafe` here: iceoryx2's safe slice API is enough.
#![forbid(unsafe_code)]

pub mod frame;
mod naming;
pub mod ports;

pub use frame::{FrameError, PolicyHeader, TransitionHeader};
pub use naming::{host_identity, new_run_id, ServiceNames};
pub use ports::{
    Cleanup, Frame, FrameHeader, PolicyFrame, PolicyLimits, PolicyPublisher, PolicySubscriber,
    Sent, ShmError, ShmNode, TransitionFrame, TransitionLimits, TransitionPublisher,
    TransitionSubscriber,
};
