//! The learner's policy network as an actor's [`Policy`]: rfcl-policy's CPU [`PolicyNet`]
//! (the tanh-Gaussian actor of spec 5.1, weights in the safetensors format the learner
//! publishes, defined by rfcl-policy).
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::RunConfig;
pub use rfcl_policy::{PolicyDescription, PolicyError, PolicyNet, PolicyShape};

use crate::policy::{LoadError, Policy};

impl Policy for PolicyNet {
    fn act(&mut self, obs: &[f32], deterministic: bool, rng: &mut ChaCha8Rng) -> Vec<f32> {
        PolicyNet::act(self, obs, deterministic, rng)
    }

    fn load(&mut self, weights: &[u8]) -> Result<(), LoadError> {
        PolicyNet::load(self, weights).map_err(Into::into)
    }
}

/// The actor network of `cfg` for these dims, with the weights of one published version.
pub fn policy_from_weights(
    weights: &[u8],
    cfg: &RunConfig,
    obs_dim: usize,
    action_dim: usize,
) -> Result<Box<dyn Policy>, PolicyError> {
    Ok(Box::new(PolicyNet::from_safetensors(
        weights, cfg, obs_dim, action_dim,
    )?))
}

/// The size of every policy version the learner publishes for `cfg` and these dims: the format
/// has fixed tensor names and shapes, so one encoded network tells them all. An actor bounds what
/// it accepts on its policy stream by it.
pub fn published_policy_bytes(
    cfg: &RunConfig,
    obs_dim: usize,
    action_dim: usize,
) -> Result<usize, PolicyError> {
    let net = PolicyNet::init(PolicyShape::from_config(cfg, obs_dim, action_dim), 0)?;
    Ok(net.to_safetensors()?.len())
}

/// Acting on the CPU from an actor process: one libtorch thread (the cores belong to the
/// learner; an actor's forward passes are tiny).
pub fn configure_inference_threads() {
    tch::set_num_threads(1);
}
