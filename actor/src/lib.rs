//! rfcl-actor: the simulator side of RFCL.
//!
//! * [`env`](mod@env): the [`Env`] trait every simulator implements for an actor (resets to seeds
//!   and to demo states, steps, flat env states; spec 2.4, 5.6).
//! * [`pointmaze`]: the native PointMaze toy task (spec 7.5) and its demo planner.
#![forbid(unsafe_code)]

pub mod env;
pub mod pointmaze;

pub use env::{Env, EnvError, StateEntry, StateKind, StateLayout, StepOutcome};
pub use pointmaze::PointMaze;
