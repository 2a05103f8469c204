//! A demo's quality check with no run (`rfcl demos inspect --replay`): every state lies inside the
//! env's domain (the env accepts it as a reset state), replaying the demo's actions from its first
//! state reproduces its states and success flags (where the simulator is deterministic), and its
//! final state is a success under the env's own check.
use rfcl_core::demo::Demo;

use crate::env::{Env, EnvError};

/// States further apart than this (max absolute difference of any value) count as diverged.
pub const STATE_TOLERANCE: f32 = 1e-3;

/// What replaying one demo found.
#[derive(Debug, Clone, PartialEq)]
pub struct ReplayCheck {
    /// The first state the env refuses as a reset state: (index, why).
    pub invalid_state: Option<(usize, String)>,
    /// Max absolute difference between a replayed state and the demo's, over the whole demo.
    pub max_state_error: f32,
    /// The first state index where the replay differs by more than [`STATE_TOLERANCE`].
    pub first_divergence: Option<usize>,
    /// Steps whose replayed success flag differs from the demo's.
    pub success_mismatches: usize,
    /// The env's own success check after the last action of the replay.
    pub final_success: bool,
}

impl ReplayCheck {
    /// Whether the demo passes every check.
    pub fn passed(&self) -> bool {
        self.invalid_state.is_none()
            && self.first_divergence.is_none()
            && self.success_mismatches == 0
            && self.final_success
    }
}

/// Checks `demo` on `env` (spec 2.4: each reset first resets with the demo's seed and options).
/// Fails only when the simulator itself fails; a refused state is a finding, not an error.
pub fn check_demo(env: &mut dyn Env, demo: &Demo) -> Result<ReplayCheck, EnvError> {
    let (seed, options) = (demo.reset.seed, &demo.reset.options);
    let states: Vec<&[f32]> = demo.env_states.chunks_exact(demo.state_dim).collect();
    let mut invalid_state = None;
    for (index, state) in states.iter().enumerate() {
        match env.reset_to_state(seed, options, state) {
            Ok(_) => {}
            Err(EnvError::Simulator { message }) => return Err(EnvError::Simulator { message }),
            Err(e) => {
                invalid_state = Some((index, e.to_string()));
                break;
            }
        }
    }
    let mut max_state_error = 0.0f32;
    let mut first_divergence = None;
    let mut success_mismatches = 0;
    let mut final_success = false;
    if invalid_state.is_none() {
        env.reset_to_state(seed, options, states[0])?;
        for (t, action) in demo.actions.chunks_exact(demo.action_dim).enumerate() {
            let outcome = env.step(action)?;
            let error = state_error(&env.get_state(), states[t + 1]);
            max_state_error = max_state_error.max(error);
            if error > STATE_TOLERANCE && first_divergence.is_none() {
                first_divergence = Some(t + 1);
            }
            success_mismatches += usize::from(outcome.success != demo.success[t]);
            final_success = outcome.success;
        }
    }
    Ok(ReplayCheck {
        invalid_state,
        max_state_error,
        first_divergence,
        success_mismatches,
        final_success,
    })
}

/// The largest absolute difference between two states (infinite when their lengths differ).
fn state_error(a: &[f32], b: &[f32]) -> f32 {
    if a.len() != b.len() {
        return f32::INFINITY;
    }
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pointmaze::demos::{demo_set, generate_demos};
    use crate::PointMaze;

    #[test]
    fn generated_pointmaze_demos_pass_and_a_moved_state_or_a_cut_demo_is_caught() {
        let set = demo_set(generate_demos(2, 0), "unused.h5");
        let mut env = PointMaze::new(0);
        for demo in &set.demos {
            let check = check_demo(&mut env, demo).unwrap();
            assert!(check.passed(), "{check:?}");
            assert!(check.max_state_error <= STATE_TOLERANCE);
        }
        // A state moved one cell along its corridor: the replay diverges there.
        let mut moved = set.demos[0].clone();
        let t = moved.len() / 2;
        moved.env_states[t * moved.state_dim] += 1.0;
        let check = check_demo(&mut env, &moved).unwrap();
        assert!(!check.passed());
        assert!(
            check.invalid_state.is_some() || check.first_divergence == Some(t),
            "{check:?}"
        );
        // A state inside a wall is refused as a reset state, with the field named.
        let mut walled = set.demos[0].clone();
        walled.env_states[..2].copy_from_slice(&[0.0, 0.0]);
        let check = check_demo(&mut env, &walled).unwrap();
        let (index, why) = check.invalid_state.unwrap();
        assert_eq!(index, 0);
        assert!(why.contains("qpos"), "{why}");
        // Cut half-way: it replays faithfully, but its final state is no success.
        let mut cut = set.demos[0].clone();
        let keep = cut.len() / 2;
        cut.actions.truncate(keep * cut.action_dim);
        cut.success.truncate(keep);
        cut.env_states.truncate((keep + 1) * cut.state_dim);
        let check = check_demo(&mut env, &cut).unwrap();
        assert!(check.first_divergence.is_none() && check.success_mismatches == 0);
        assert!(!check.final_success && !check.passed(), "{check:?}");
    }
}
