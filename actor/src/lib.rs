//! rfcl-actor: the simulator side of RFCL.
//!
//! * [`env`](mod@env): the [`Env`] trait every simulator implements for an actor (resets to seeds
//!   and to demo states, steps, flat env states; spec 2.4, 5.6).
//! * [`pointmaze`]: the native PointMaze toy task (spec 7.5) and its demo planner.
//! * [`python`]: the Python simulators (ManiSkill3, MetaWorld, Adroit) as envs, each served by an
//!   `rfcl-sim-worker` process.
//! * [`suite`]: which envs an actor can make for a run's env config.
//! * [`policy`]: the [`Policy`] an actor acts with, and uniform exploration (spec 5.4).
//! * [`net`]: the learner's policy network ([`net::PolicyNet`], from rfcl-policy) as a [`Policy`].
//! * [`rollout`]: K envs stepped from reset leases into transitions and episode reports (spec 2.4,
//!   2.5, 5.4-5.6), pure logic shared by the `actor` binary and `rfcl eval`.
//! * [`replay`]: a demo's quality check with no run: its states are valid reset states and its
//!   actions replay into its states and success (`rfcl demos inspect --replay`).
//! * [`eval`]: when eval actors evaluate and how many episodes (spec 5.7).
//! * [`retry`]: backoff with a deadline for lost connections.
//! * [`bench`]: `rfcl bench actor`, the actor's overhead over a bare env loop.
//!
//! * [`service`]: the actor service, `serve(options, shutdown)`: the transport shell around
//!   [`rollout::Rollout`] (gRPC and shared-memory links, train and eval loops). The `actor`
//!   binary (`src/bin/actor.rs`) parses its flags and calls it.
#![forbid(unsafe_code)]

pub mod bench;
pub mod env;
pub mod eval;
pub mod net;
pub mod pointmaze;
pub mod policy;
pub mod python;
pub mod replay;
mod retry;
pub mod rollout;
pub mod service;
pub mod suite;
pub mod video;

pub use env::{Env, EnvError, StateEntry, StateKind, StateLayout, StepOutcome};
pub use pointmaze::PointMaze;
pub use policy::{Policy, PolicyHandle};
pub use rollout::{Rollout, RolloutSettings, StepOutput};
