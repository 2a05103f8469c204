//! [`PolicyNet`]: the actor on the CPU with loaded weights, what actors and `rfcl eval` act with.
use std::path::Path;

use rand::Rng;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rfcl_core::config::{MatmulPrecision, RunConfig};
use tch::{nn, Device, Tensor};

use crate::format::{encode_vars, load_vars, PolicyDescription, PolicyError, PolicyShape};
use crate::mlp::Actor;

/// The actor on the CPU, for acting (actors, `rfcl eval`, tests). Always f32 and
/// [`MatmulPrecision::Fp32`]: acting is a few tiny matmuls, and every consumer of the weights then
/// computes the same actions whatever precision the learner trained in.
#[derive(Debug)]
pub struct PolicyNet {
    vs: nn::VarStore,
    actor: Actor,
    shape: PolicyShape,
}

impl PolicyNet {
    /// A freshly initialised actor of `shape` (spec 5.1 init, weights drawn from
    /// `ChaCha8Rng::seed_from_u64(seed)`): a valid policy without a learner, for benchmarks,
    /// examples and tests. With a run's seed and config it equals the initial actor of that run's
    /// learner (the learner draws the actor first from the same seeded RNG), i.e. published
    /// policy version 1.
    pub fn init(shape: PolicyShape, seed: u64) -> Result<Self, PolicyError> {
        shape.check()?;
        let vs = nn::VarStore::new(Device::Cpu);
        let actor = Actor::new(
            &vs.root(),
            &mut ChaCha8Rng::seed_from_u64(seed),
            shape.obs_dim as i64,
            shape.action_dim as i64,
            &shape.network(),
            MatmulPrecision::Fp32,
        );
        Ok(Self { vs, actor, shape })
    }

    /// Builds the actor of `cfg` for these dims on the CPU and loads `bytes` into it.
    pub fn from_safetensors(
        bytes: &[u8],
        cfg: &RunConfig,
        obs_dim: usize,
        action_dim: usize,
    ) -> Result<Self, PolicyError> {
        Self::from_shape(bytes, PolicyShape::from_config(cfg, obs_dim, action_dim))
    }

    /// Builds an actor of `shape` on the CPU and loads `bytes` into it.
    pub fn from_shape(bytes: &[u8], shape: PolicyShape) -> Result<Self, PolicyError> {
        // The init is overwritten by the weights; a fixed seed keeps construction deterministic.
        let net = Self::init(shape, 0)?;
        net.load(bytes)?;
        Ok(net)
    }

    /// Loads an exported policy: `policy.safetensors` and `policy.json` in `dir`.
    pub fn from_export(dir: &Path) -> Result<(Self, PolicyDescription), PolicyError> {
        let read = |name: &str| {
            let path = dir.join(name);
            std::fs::read(&path).map_err(|source| PolicyError::Io {
                path: path.display().to_string(),
                source,
            })
        };
        let desc = PolicyDescription::from_json(&String::from_utf8_lossy(&read("policy.json")?))?;
        let net = Self::from_shape(&read("policy.safetensors")?, desc.shape.clone())?;
        Ok((net, desc))
    }

    /// Replaces the weights in place with a newer version (no rebuild, no allocation of new
    /// variables): what an actor does with each `PolicyWeights` it receives.
    pub fn load(&self, bytes: &[u8]) -> Result<(), PolicyError> {
        load_vars(&self.vs, bytes)
    }

    pub fn shape(&self) -> &PolicyShape {
        &self.shape
    }
    pub fn obs_dim(&self) -> usize {
        self.shape.obs_dim
    }
    pub fn action_dim(&self) -> usize {
        self.shape.action_dim
    }

    /// The weights as safetensors bytes (the format of the crate docs).
    pub fn to_safetensors(&self) -> Result<Vec<u8>, PolicyError> {
        encode_vars(&self.vs)
    }

    /// One action for one observation: a stochastic tanh-Gaussian sample for training
    /// (spec 5.4) or tanh(μ) when `deterministic` (evaluation, spec 5.7).
    ///
    /// # Panics
    /// When `obs.len()` is not `obs_dim` (the dims come from the run description).
    pub fn act<R: Rng + ?Sized>(&self, obs: &[f32], deterministic: bool, rng: &mut R) -> Vec<f32> {
        assert_eq!(
            obs.len(),
            self.shape.obs_dim,
            "PolicyNet::act: obs has {} values, the policy takes obs_dim {}",
            obs.len(),
            self.shape.obs_dim
        );
        self.act_batch(obs, deterministic, rng)
    }

    /// Actions for `obs.len() / obs_dim` observations, row-major (`[N, obs_dim]` in,
    /// `[N, action_dim]` out). Noise is drawn row by row from `rng`, so a batch of N gives the
    /// same actions as N calls of [`act`](Self::act) with the same RNG.
    ///
    /// # Panics
    /// When `obs.len()` is not a multiple of `obs_dim`.
    pub fn act_batch<R: Rng + ?Sized>(
        &self,
        obs: &[f32],
        deterministic: bool,
        rng: &mut R,
    ) -> Vec<f32> {
        let (d, a) = (self.shape.obs_dim, self.shape.action_dim);
        assert!(
            obs.len().is_multiple_of(d),
            "PolicyNet::act_batch: {} obs values are not rows of obs_dim {d}",
            obs.len()
        );
        let rows = (obs.len() / d) as i64;
        if rows == 0 {
            return Vec::new();
        }
        let obs = Tensor::from_slice(obs).view([rows, d as i64]);
        let action = tch::no_grad(|| {
            if deterministic {
                self.actor.deterministic(&obs)
            } else {
                let noise: Vec<f32> = (0..rows as usize * a)
                    .map(|_| rng.sample(StandardNormal))
                    .collect();
                let noise = Tensor::from_slice(&noise).view([rows, a as i64]);
                self.actor.sample(&obs, &noise).action
            }
        });
        Vec::<f32>::try_from(action.view([-1])).expect("an f32 action tensor")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::{tensor_names, FORMAT};
    use safetensors::tensor::{Dtype, SafeTensors};

    fn small() -> RunConfig {
        let mut cfg = RunConfig::default();
        cfg.network.actor_features = vec![8, 6];
        cfg.network.critic_features = vec![8];
        cfg
    }

    fn random(cfg: &RunConfig, obs: usize, act: usize, seed: u64) -> PolicyNet {
        PolicyNet::init(PolicyShape::from_config(cfg, obs, act), seed).unwrap()
    }

    /// The row-major `[rows, cols]` f32 values of tensor `name` in safetensors `bytes`.
    fn values(bytes: &[u8], name: &str) -> Vec<f64> {
        let file = SafeTensors::deserialize(bytes).unwrap();
        let view = file.tensor(name).unwrap();
        view.data()
            .chunks(4)
            .map(|b| f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])))
            .collect()
    }

    /// tanh(μ) computed from the weights with plain f64 loops, as the crate docs describe the
    /// format: what a loader in another language would compute.
    fn documented_deterministic(bytes: &[u8], layers: usize, obs: &[f64]) -> Vec<f64> {
        let dense = |x: &[f64], name: &str, relu: bool| {
            let (kernel, bias) = (
                values(bytes, &format!("{name}.kernel")),
                values(bytes, &format!("{name}.bias")),
            );
            let out = bias.len();
            (0..out)
                .map(|j| {
                    let y = bias[j]
                        + x.iter()
                            .enumerate()
                            .map(|(i, xi)| xi * kernel[i * out + j])
                            .sum::<f64>();
                    if relu {
                        y.max(0.0)
                    } else {
                        y
                    }
                })
                .collect::<Vec<f64>>()
        };
        let mut h = obs.to_vec();
        for i in 0..layers {
            h = dense(&h, &format!("trunk{i}"), true);
        }
        dense(&h, "mean", false).iter().map(|m| m.tanh()).collect()
    }

    #[test]
    fn round_trip_gives_the_same_actions() {
        let cfg = small();
        let original = random(&cfg, 5, 3, 11);
        let bytes = original.to_safetensors().unwrap();
        let net = PolicyNet::from_safetensors(&bytes, &cfg, 5, 3).unwrap();
        let obs: Vec<f32> = (0..20).map(|i| (i as f32 * 0.37).sin()).collect();
        let ours = net.act_batch(&obs, true, &mut ChaCha8Rng::seed_from_u64(1));
        let theirs = original.act_batch(&obs, true, &mut ChaCha8Rng::seed_from_u64(1));
        assert_eq!(ours, theirs);
        assert!(ours.iter().all(|a| a.abs() < 1.0));
        for (row, actions) in obs.chunks(5).zip(ours.chunks(3)) {
            let row: Vec<f64> = row.iter().map(|&x| f64::from(x)).collect();
            let expected = documented_deterministic(&bytes, 2, &row);
            for (a, e) in actions.iter().zip(&expected) {
                assert!((f64::from(*a) - e).abs() < 1e-5, "{a} vs {e}");
            }
        }
        // Stochastic actions differ from the deterministic ones and stay in (-1, 1).
        let sampled = net.act(&obs[..5], false, &mut ChaCha8Rng::seed_from_u64(2));
        assert_eq!(sampled.len(), 3);
        assert_ne!(sampled, ours[..3].to_vec());
        assert!(sampled.iter().all(|a| a.abs() < 1.0));
        assert_eq!(net.to_safetensors().unwrap(), bytes);
    }

    #[test]
    fn init_is_a_function_of_the_seed() {
        let cfg = small();
        let bytes = |seed| random(&cfg, 4, 2, seed).to_safetensors().unwrap();
        assert_eq!(bytes(7), bytes(7));
        assert_ne!(bytes(7), bytes(8));
        // Spec 5.1 init: every bias zero.
        for name in tensor_names(2).iter().filter(|n| n.ends_with(".bias")) {
            assert!(values(&bytes(7), name).iter().all(|&b| b == 0.0), "{name}");
        }
        let mut flat = PolicyShape::from_config(&cfg, 4, 2);
        flat.actor_features.clear();
        assert!(matches!(
            PolicyNet::init(flat, 0),
            Err(PolicyError::Config(_))
        ));
        let mut inverted = PolicyShape::from_config(&cfg, 4, 2);
        inverted.log_std_min = inverted.log_std_max;
        assert!(matches!(
            PolicyNet::init(inverted, 0),
            Err(PolicyError::Config(_))
        ));
    }

    #[test]
    fn batch_equals_row_by_row_with_the_same_rng() {
        let cfg = small();
        let net = random(&cfg, 4, 2, 3);
        let obs: Vec<f32> = (0..12).map(|i| i as f32 / 10.0 - 0.5).collect();
        let batch = net.act_batch(&obs, false, &mut ChaCha8Rng::seed_from_u64(9));
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let rows: Vec<f32> = obs
            .chunks(4)
            .flat_map(|o| net.act(o, false, &mut rng))
            .collect();
        assert_eq!(batch, rows);
    }

    #[test]
    fn load_replaces_weights_in_place() {
        let cfg = small();
        let (a, b) = (random(&cfg, 4, 2, 1), random(&cfg, 4, 2, 2));
        let net = PolicyNet::from_safetensors(&a.to_safetensors().unwrap(), &cfg, 4, 2).unwrap();
        let obs = [0.1, -0.2, 0.3, 0.4];
        let before = net.act(&obs, true, &mut ChaCha8Rng::seed_from_u64(0));
        net.load(&b.to_safetensors().unwrap()).unwrap();
        let after = net.act(&obs, true, &mut ChaCha8Rng::seed_from_u64(0));
        assert_ne!(before, after);
        assert_eq!(after, b.act(&obs, true, &mut ChaCha8Rng::seed_from_u64(0)));
    }

    #[test]
    fn mismatched_weights_are_rejected_by_name() {
        let cfg = small();
        let bytes = random(&cfg, 5, 3, 0).to_safetensors().unwrap();
        match PolicyNet::from_safetensors(&bytes, &cfg, 6, 3) {
            Err(PolicyError::Shape { name, .. }) => assert_eq!(name, "trunk0.kernel"),
            other => panic!("expected a shape error, got {other:?}"),
        }
        let mut wider = cfg.clone();
        wider.network.actor_features = vec![8, 6, 4];
        match PolicyNet::from_safetensors(&bytes, &wider, 5, 3) {
            Err(PolicyError::Missing(name)) => assert_eq!(name, "trunk2.bias"),
            other => panic!("expected a missing tensor, got {other:?}"),
        }
        let mut narrower = cfg.clone();
        narrower.network.actor_features = vec![8];
        match PolicyNet::from_safetensors(&bytes, &narrower, 5, 3) {
            Err(PolicyError::Unexpected(name)) => assert_eq!(name, "trunk1.bias"),
            other => panic!("expected an unexpected tensor, got {other:?}"),
        }
        match PolicyNet::from_safetensors(&bytes, &cfg, 5, 2) {
            Err(PolicyError::Shape { name, .. }) => assert_eq!(name, "log_std.bias"),
            other => panic!("expected a shape error, got {other:?}"),
        }
        assert!(matches!(
            PolicyNet::from_safetensors(b"not safetensors", &cfg, 5, 3),
            Err(PolicyError::Safetensors(_))
        ));
    }

    #[test]
    fn metadata_and_names_follow_the_documented_format() {
        let cfg = small();
        let bytes = random(&cfg, 5, 3, 0).to_safetensors().unwrap();
        let (_, meta) = SafeTensors::read_metadata(&bytes).unwrap();
        let meta = meta.metadata().clone().unwrap();
        assert_eq!(meta["format"], FORMAT);
        assert_eq!(meta.len(), 1);
        let file = SafeTensors::deserialize(&bytes).unwrap();
        let mut names: Vec<String> = file.names().into_iter().map(String::from).collect();
        names.sort();
        let mut expected = tensor_names(2);
        expected.sort();
        assert_eq!(names, expected);
        assert_eq!(file.tensor("trunk0.kernel").unwrap().shape(), &[5, 8]);
        assert_eq!(file.tensor("mean.bias").unwrap().dtype(), Dtype::F32);
    }

    #[test]
    fn an_export_loads_with_its_description() {
        let cfg = small();
        let net = random(&cfg, 5, 3, 4);
        let shape = net.shape().clone();
        let desc = PolicyDescription {
            format: FORMAT.into(),
            env_id: "PointMaze".into(),
            tensors: tensor_names(shape.actor_features.len()),
            shape,
            activation: "relu".into(),
            action_scale: Some(vec![0.5, 1.0, 2.0]),
            policy_version: 3,
            env_steps: 120,
        };
        let dir = tempfile::tempdir().unwrap();
        let bytes = net.to_safetensors().unwrap();
        std::fs::write(dir.path().join("policy.safetensors"), &bytes).unwrap();
        std::fs::write(dir.path().join("policy.json"), desc.to_json()).unwrap();
        let (loaded, read) = PolicyNet::from_export(dir.path()).unwrap();
        assert_eq!(read, desc);
        assert_eq!(loaded.to_safetensors().unwrap(), bytes);
        std::fs::remove_file(dir.path().join("policy.json")).unwrap();
        assert!(matches!(
            PolicyNet::from_export(dir.path()),
            Err(PolicyError::Io { .. })
        ));
    }
}
