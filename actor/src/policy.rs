//! What a rollout needs from a policy, and the exploration rule of spec 5.4.
//!
//! The actor holds the latest policy the learner published ([`PolicyHandle`]: the network plus the
//! version and the learner's env-step count at publication). Rollouts ask it for one action per
//! env step; the network behind [`Policy`] is the learner's tanh-Gaussian actor (spec 5.1), kept
//! behind a trait so that the rollout logic is tested without libtorch.
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Why a policy refused new weights.
pub type LoadError = Box<dyn std::error::Error + Send + Sync>;

/// An acting policy: one observation in, one action in `[-1, 1]^A` out.
pub trait Policy: Send {
    /// A sample of π(·|obs) (training, spec 5.4), or the deterministic action tanh(μ)
    /// (evaluation, spec 5.7) when `deterministic`. `rng` is the env's own stream, so a run's
    /// actions depend only on its seeds.
    fn act(&mut self, obs: &[f32], deterministic: bool, rng: &mut ChaCha8Rng) -> Vec<f32>;

    /// Replaces the weights in place with a newer version's (the learner's safetensors bytes).
    fn load(&mut self, weights: &[u8]) -> Result<(), LoadError>;
}

/// A published policy version as an actor holds it.
pub struct PolicyHandle {
    /// The learner's policy version (transitions and reports carry it).
    pub version: u64,
    /// Env steps the learner had received when it published this version: eval results are keyed
    /// by it (spec 5.7), and it decides the end of uniform exploration (spec 5.4).
    pub env_steps: u64,
    pub policy: Box<dyn Policy>,
}

impl std::fmt::Debug for PolicyHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PolicyHandle")
            .field("version", &self.version)
            .field("env_steps", &self.env_steps)
            .finish_non_exhaustive()
    }
}

/// Spec 5.4: in stage 1, actions are uniform in `[-1, 1]^A` while the run has taken fewer than
/// `num_seed_steps` env steps; the stochastic policy acts after that. The actor judges the run's
/// step count by the newest policy it holds (`policy_env_steps`, the learner's count when it
/// published), so it also explores uniformly before it has any policy. Stage-2 leases always use
/// the policy: its seed steps are policy-driven (spec 4.4).
pub fn explores_uniformly(stage: u32, policy_env_steps: Option<u64>, num_seed_steps: u64) -> bool {
    match policy_env_steps {
        None => true,
        Some(steps) => stage <= 1 && steps < num_seed_steps,
    }
}

/// A uniform action in `[-1, 1]^A` (spec 5.4).
pub fn uniform_action(action_dim: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
    (0..action_dim)
        .map(|_| rng.random_range(-1.0f32..=1.0))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn uniform_exploration_follows_spec_5_4() {
        // No policy yet: uniform, whatever the stage.
        assert!(explores_uniformly(1, None, 5000));
        assert!(explores_uniformly(2, None, 5000));
        // Stage 1: uniform below the seed steps, the policy from then on.
        assert!(explores_uniformly(1, Some(0), 5000));
        assert!(explores_uniformly(1, Some(4999), 5000));
        assert!(!explores_uniformly(1, Some(5000), 5000));
        // Stage 2's seed steps are policy-driven.
        assert!(!explores_uniformly(2, Some(10), 5000));
    }

    #[test]
    fn uniform_actions_cover_the_box() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let actions: Vec<f32> = (0..2000)
            .flat_map(|_| uniform_action(2, &mut rng))
            .collect();
        assert!(actions.iter().all(|a| (-1.0..=1.0).contains(a)));
        assert!(actions.iter().any(|a| *a < -0.95) && actions.iter().any(|a| *a > 0.95));
        let mean = actions.iter().sum::<f32>() / actions.len() as f32;
        assert!(mean.abs() < 0.05, "mean {mean}");
    }
}
