//! Reset leases and episode reports: the curriculum contract (docs/DESIGN.md, "The path of a lease"), as domain types.
//!
//! The wire forms live in rfcl-proto; `rfcl_proto::convert` is the one place that converts between
//! the two.
use serde::{Deserialize, Serialize};

/// Seed and options for the simulator's reset, applied before any env state (spec 2.4): the same
/// type the demo files carry.
pub use crate::demo::ResetArgs;

/// What kind of reset a lease asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum LeaseKind {
    /// Stage 1: reset with the demo's seed/options, then set the simulator to a demo state (spec 2.4).
    DemoState,
    /// Stage 2: a forward-curriculum level (spec 3).
    Level,
    /// Evaluation on a held-out seed of the true initial-state distribution (spec 5.7).
    Eval,
}

/// Where one episode starts, handed out by the curriculum server.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ResetLease {
    pub lease_id: u64,
    pub kind: LeaseKind,
    pub demo_id: u32,
    pub start_index: u32,
    /// Flat simulator state; empty when the reset is from a seed alone.
    pub env_state: Vec<f32>,
    pub reset: ResetArgs,
    /// Steps after which the episode is truncated.
    pub time_limit: u32,
    pub stage: u32,
    pub stage_epoch: u64,
    /// Forward-curriculum level (LEVEL leases).
    pub level: u32,
}

/// What an actor asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct AcquireRequest {
    pub actor_id: u32,
    pub env_index: u32,
    pub eval: bool,
}

/// The outcome of one leased episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeReport {
    pub lease_id: u64,
    pub success_at_end: bool,
    pub success_once: bool,
    pub episode_return: f64,
    pub length: u32,
    pub policy_version: u64,
    pub stage_epoch: u64,
    pub actor_id: u32,
    pub actor_env_steps: u64,
    /// Env steps the learner had received when it published `policy_version`.
    pub policy_env_steps: u64,
    /// Simulator worker restarts of this actor process so far (heartbeat, like `actor_env_steps`).
    /// A crashed or hung Python worker is restarted and its episode replayed, so the episode
    /// itself shows nothing: this count is how the run sees it.
    #[serde(default)]
    pub sim_restarts: u64,
    /// Why the actor could not reset its env to the lease's state, when it could not: the episode
    /// never ran (`length` 0, no success), and the curriculum counts the failure against the
    /// lease's demo instead of as an outcome.
    #[serde(default)]
    pub reset_failure: Option<String>,
}

/// The longest reset-failure reason a report carries, in bytes; an actor shortens longer ones
/// (a Python traceback) with [`shorten_reason`].
pub const MAX_RESET_FAILURE_BYTES: usize = 2048;

/// `reason` cut to at most [`MAX_RESET_FAILURE_BYTES`] bytes on a character boundary, its end
/// kept (a traceback's last line says what failed).
pub fn shorten_reason(reason: &str) -> String {
    if reason.len() <= MAX_RESET_FAILURE_BYTES {
        return reason.to_owned();
    }
    let marker = "...";
    let mut start = reason.len() - (MAX_RESET_FAILURE_BYTES - marker.len());
    while !reason.is_char_boundary(start) {
        start += 1;
    }
    format!("{marker}{}", &reason[start..])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_reason_keeps_its_end_within_the_bound() {
        assert_eq!(shorten_reason("bad state"), "bad state");
        let traceback = format!("{}ValueError: qpos is NaN", "é".repeat(2000));
        let short = shorten_reason(&traceback);
        assert!(short.len() <= MAX_RESET_FAILURE_BYTES, "{}", short.len());
        assert!(short.starts_with("..."));
        assert!(short.ends_with("ValueError: qpos is NaN"));
    }
}
