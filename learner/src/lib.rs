//! RFCL learner library: batched-ensemble SAC on libtorch and its replay (spec 5, 6.2-6.4, 4.2),
//! and the learner service around them. The maths and the replay do no I/O; the service modules
//! below wire them to the transports, and the `learner` binary parses flags, loads, binds and calls
//! [`server`].
//!
//! * [`nets`]: the critic ensemble (one batched computation) and its initialisers, with the actor
//!   (the tanh-Gaussian policy) of rfcl-policy (spec 5.1).
//! * [`sac`]: the losses and the training iteration (spec 5.2, 5.3), metrics of spec 5.8.
//! * [`fused`]: the critic's loss and gradients on the CPU with the elementwise work fused
//!   (`learner.backend: fused`).
//! * [`members`]: the critic ensemble's members run on several threads (the member-parallel
//!   execution of [`Sac::set_member_threads`]).
//! * [`adam`]: in-place Adam whose state can be checkpointed (spec 5.3, 4.1).
//! * [`replay`]: online/offline rings, 50/50 interleaved sampling, demos as offline data with
//!   `data_action_scale`, the stage transition (spec 5.5, 6.2, 6.4, 4.2, 12.7).
//! * [`batch`]: the tensors one iteration consumes.
//! * [`bench`]: updates/s and FLOPs of the SAC update (`rfcl bench learner`).
//! * [`metrics`], [`tensorboard`], [`prom`]: `metrics.csv`, TensorBoard event files and the
//!   Prometheus `/metrics` state (spec 5.8; docs/LEARNER.md).
//! * [`error`]: the library's error type and the one-line rendering of a cause chain.
//! * [`runtime`]: process-wide CPU settings (threads, allocator) for the SAC maths.
//! * [`ingest`], [`service`], [`shm`]: transitions in over gRPC and iceoryx2 shared memory into
//!   one validated, bounded ingest path, policy versions out over both, counted per transport.
//!   Policy versions are in the weights format of rfcl-policy.
//! * [`stages`], [`checkpoint`], [`trainer`], [`limiter`]: the stage subscription, crash-safe
//!   checkpoints, the training loop and its update-to-data limiter.
//! * [`server`]: the learner service, `Server::start(bound, inputs)` then `serve(stops)`: the
//!   training thread, gRPC, metrics and the stage subscription as named tasks under one
//!   supervisor.
pub mod adam;
mod batch;
pub mod bench;
pub mod checkpoint;
mod error;
pub mod fused;
pub mod ingest;
pub mod limiter;
mod members;
mod metrics;
pub mod nets;
mod prom;
pub mod replay;
pub mod runtime;
pub mod sac;
pub mod server;
pub mod service;
pub mod shm;
pub mod stages;
pub mod tensorboard;
pub mod trainer;

pub use batch::{Batch, HostBatch};
pub use error::{LearnerError, Result};
pub use replay::{Replay, ReplayBuffer};
pub use sac::{Sac, UpdateMetrics};
