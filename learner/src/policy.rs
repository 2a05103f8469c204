//! The policy weights format shared by the learner and the actors (ARCHITECTURE "Contracts",
//! "Policy weights"), and the CPU policy that acts with them (spec 5.1, 5.4, 5.7).
//!
//! # Wire format
//!
//! A policy version travels as the [safetensors](https://github.com/huggingface/safetensors)
//! bytes of the actor network alone (`PolicyWeights.safetensors`, and `policy.safetensors` in a
//! run directory). Tensor names are the actor var store's variable names, all `f32`, Flax layout
//! (`y = x · kernel + bias`, `kernel` `[fan_in, fan_out]`):
//!
//! | name                               | shape                | role                         |
//! |------------------------------------|----------------------|------------------------------|
//! | `trunk{i}.kernel`, `trunk{i}.bias` | `[in, H_i]`, `[H_i]` | hidden layer i, then ReLU    |
//! | `mean.kernel`, `mean.bias`         | `[H, A]`, `[A]`      | μ, the pre-tanh mean         |
//! | `log_std.kernel`, `log_std.bias`   | `[H, A]`, `[A]`      | h, the raw log-std head      |
//!
//! log σ = min + ½(max − min)(tanh(h) + 1) with the run's `network.log_std_min/max`. A training
//! actor samples a = tanh(μ + σ·ε), ε ~ N(0, I); an eval actor takes tanh(μ) (spec 5.7). Actions
//! are in agent units, in (−1, 1); with `train.data_action_scale` the env action is a / s
//! clipped to [−1, 1] (spec 6.4), with the s that [`PolicyDescription::action_scale`] records for
//! exported policies and `RunInfo.action_scale` gives actors.
//!
//! The safetensors header metadata holds one entry, `format` = [`FORMAT`] (one entry keeps the
//! bytes deterministic: equal weights give equal bytes); the dims are the shapes of
//! `trunk0.kernel` (`[obs_dim, H_0]`) and `mean.bias` (`[action_dim]`).
use std::collections::HashMap;
use std::path::Path;

use rand::Rng;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rfcl_core::config::{MatmulPrecision, NetworkConfig, RunConfig};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use tch::{nn, Device, Kind, Tensor};
use thiserror::Error;

use crate::nets::Actor;
use crate::sac::Sac;

/// The `format` metadata value of actor weights written by [`encode_actor`].
pub const FORMAT: &str = "rfcl-actor-v1";

/// Why policy weights could not be encoded or loaded. Causes are sources, never repeated in the
/// message (see [`crate::error`]).
#[derive(Debug, Error)]
pub enum PolicyError {
    #[error("policy weights are not valid safetensors")]
    Safetensors(#[from] safetensors::SafeTensorError),
    #[error("policy weights lack tensor {0:?} of the actor network")]
    Missing(String),
    #[error("policy weights have tensor {0:?}, which the actor network does not have")]
    Unexpected(String),
    #[error("policy tensor {name:?} has shape {got:?}, the actor network expects {expected:?}")]
    Shape {
        name: String,
        expected: Vec<i64>,
        got: Vec<usize>,
    },
    #[error("policy tensor {name:?} is {dtype:?}; expected F32 (or F64)")]
    Dtype { name: String, dtype: Dtype },
    #[error("invalid policy shape: {0}")]
    Config(String),
    #[error("policy description (policy.json)")]
    Description(#[from] serde_json::Error),
    #[error("{path}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("libtorch")]
    Torch(#[from] tch::TchError),
}

/// What a policy network looks like: everything needed to rebuild it from its weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolicyShape {
    pub obs_dim: usize,
    pub action_dim: usize,
    /// Hidden widths of the actor trunk (`network.actor_features`).
    pub actor_features: Vec<u32>,
    pub log_std_min: f64,
    pub log_std_max: f64,
}

impl PolicyShape {
    /// The actor of a run config for the given dims.
    pub fn from_config(cfg: &RunConfig, obs_dim: usize, action_dim: usize) -> Self {
        Self {
            obs_dim,
            action_dim,
            actor_features: cfg.network.actor_features.clone(),
            log_std_min: cfg.network.log_std_min,
            log_std_max: cfg.network.log_std_max,
        }
    }

    fn check(&self) -> Result<(), PolicyError> {
        if self.obs_dim == 0 || self.action_dim == 0 {
            return Err(PolicyError::Config(format!(
                "obs_dim {} and action_dim {} must be positive",
                self.obs_dim, self.action_dim
            )));
        }
        if self.actor_features.is_empty() || self.actor_features.contains(&0) {
            return Err(PolicyError::Config(format!(
                "actor_features {:?} needs at least one layer, all positive",
                self.actor_features
            )));
        }
        if self.log_std_min.is_nan()
            || self.log_std_max.is_nan()
            || self.log_std_min >= self.log_std_max
        {
            return Err(PolicyError::Config(format!(
                "log_std_min ({}) must be below log_std_max ({})",
                self.log_std_min, self.log_std_max
            )));
        }
        Ok(())
    }

    fn network(&self) -> NetworkConfig {
        NetworkConfig {
            actor_features: self.actor_features.clone(),
            log_std_min: self.log_std_min,
            log_std_max: self.log_std_max,
            ..NetworkConfig::default()
        }
    }
}

/// The exported policy's description, `policy.json` next to `policy.safetensors` in a run
/// directory (see `docs/POLICY.md` for a PyTorch loader).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolicyDescription {
    /// [`FORMAT`].
    pub format: String,
    pub env_id: String,
    #[serde(flatten)]
    pub shape: PolicyShape,
    /// Hidden layers: `relu(x · kernel + bias)`.
    pub activation: String,
    /// Per action dim, the s of spec 6.4: the env action is `clip(a / s, −1, 1)`. `None`: env
    /// action = a.
    pub action_scale: Option<Vec<f32>>,
    /// The policy version and the env steps the learner had received when it was published.
    pub policy_version: u64,
    pub env_steps: u64,
    /// Tensor names in the safetensors file, in forward order.
    pub tensors: Vec<String>,
}

impl PolicyDescription {
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a policy description serialises")
    }

    pub fn from_json(text: &str) -> Result<Self, PolicyError> {
        Ok(serde_json::from_str(text)?)
    }
}

/// The tensor names of an actor with `layers` hidden layers, in forward order.
pub fn tensor_names(layers: usize) -> Vec<String> {
    let mut names = Vec::new();
    for i in 0..layers {
        names.push(format!("trunk{i}.kernel"));
        names.push(format!("trunk{i}.bias"));
    }
    for head in ["mean", "log_std"] {
        names.push(format!("{head}.kernel"));
        names.push(format!("{head}.bias"));
    }
    names
}

/// The actor network of `sac` as safetensors bytes (the policy weights of one version).
pub fn encode_actor(sac: &Sac) -> Result<Vec<u8>, PolicyError> {
    encode_vars(sac.actor_vars())
}

/// Every variable of an actor var store as `f32` safetensors bytes, sorted by name, with the
/// metadata of the module docs. Tensors on a GPU are copied to the host.
pub fn encode_vars(vs: &nn::VarStore) -> Result<Vec<u8>, PolicyError> {
    let mut vars: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    let mut owned: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::with_capacity(vars.len());
    for (name, tensor) in vars {
        let host = tensor
            .detach()
            .to_device(Device::Cpu)
            .to_kind(Kind::Float)
            .contiguous();
        let numel = host.numel();
        let mut bytes = vec![0u8; numel * 4];
        host.f_copy_data_u8(&mut bytes, numel)?;
        let shape = host.size().iter().map(|&d| d as usize).collect();
        owned.push((name, shape, bytes));
    }
    let views = owned
        .iter()
        .map(|(name, shape, bytes)| {
            Ok((
                name.as_str(),
                TensorView::new(Dtype::F32, shape.clone(), bytes)?,
            ))
        })
        .collect::<Result<Vec<_>, PolicyError>>()?;
    let metadata = HashMap::from([("format".to_string(), FORMAT.to_string())]);
    Ok(safetensors::serialize(views, Some(metadata))?)
}

/// Copies safetensors `bytes` into the variables of `vs`: every variable must be present with
/// its shape, and no other tensor may be (F32 or F64 accepted, converted to the var's kind).
pub fn load_vars(vs: &nn::VarStore, bytes: &[u8]) -> Result<(), PolicyError> {
    let file = SafeTensors::deserialize(bytes)?;
    // Sorted, so the error names the same tensor every time.
    let mut vars: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    let mut names = file.names();
    names.sort();
    if let Some(extra) = names.iter().find(|n| !vars.iter().any(|(v, _)| v == **n)) {
        return Err(PolicyError::Unexpected(extra.to_string()));
    }
    if let Some((missing, _)) = vars.iter().find(|(n, _)| !names.contains(&n.as_str())) {
        return Err(PolicyError::Missing(missing.clone()));
    }
    tch::no_grad(|| {
        for (name, var) in &vars {
            let view = file
                .tensor(name)
                .map_err(|_| PolicyError::Missing(name.clone()))?;
            let expected = var.size();
            let got: Vec<usize> = view.shape().to_vec();
            if got.len() != expected.len()
                || got.iter().zip(&expected).any(|(&g, &e)| g as i64 != e)
            {
                return Err(PolicyError::Shape {
                    name: name.clone(),
                    expected,
                    got,
                });
            }
            let kind = match view.dtype() {
                Dtype::F32 => Kind::Float,
                Dtype::F64 => Kind::Double,
                dtype => {
                    return Err(PolicyError::Dtype {
                        name: name.clone(),
                        dtype,
                    })
                }
            };
            let src = Tensor::f_from_data_size(view.data(), &expected, kind)?;
            var.shallow_clone().f_copy_(&src)?;
        }
        Ok(())
    })
}

/// The actor on the CPU, for acting (actors, `rfcl eval`, tests).
#[derive(Debug)]
pub struct PolicyNet {
    vs: nn::VarStore,
    actor: Actor,
    shape: PolicyShape,
}

impl PolicyNet {
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
        shape.check()?;
        let vs = nn::VarStore::new(Device::Cpu);
        // The init is overwritten by the weights; a fixed seed keeps construction deterministic.
        let actor = Actor::new(
            &vs.root(),
            &mut ChaCha8Rng::seed_from_u64(0),
            shape.obs_dim as i64,
            shape.action_dim as i64,
            &shape.network(),
            MatmulPrecision::Fp32,
        );
        let net = Self { vs, actor, shape };
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

    /// The weights as safetensors bytes again (same format as [`encode_actor`]).
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
    use rfcl_core::config::SacConfig;

    fn small() -> RunConfig {
        let mut cfg = RunConfig::default();
        cfg.network.actor_features = vec![8, 6];
        cfg.network.critic_features = vec![8];
        cfg.sac = SacConfig {
            critic_ensemble: 2,
            target_pool: 2,
            ..SacConfig::default()
        };
        cfg
    }

    #[test]
    fn round_trip_gives_the_same_deterministic_actions() {
        let cfg = small();
        let mut sac = Sac::new(5, 3, &cfg.sac, &cfg.network, 11).unwrap();
        let bytes = encode_actor(&sac).unwrap();
        let net = PolicyNet::from_safetensors(&bytes, &cfg, 5, 3).unwrap();
        let obs: Vec<f32> = (0..20).map(|i| (i as f32 * 0.37).sin()).collect();
        let ours = net.act_batch(&obs, true, &mut ChaCha8Rng::seed_from_u64(1));
        let theirs = Vec::<f32>::try_from(
            sac.act_deterministic(&Tensor::from_slice(&obs).view([4, 5]))
                .view([-1]),
        )
        .unwrap();
        assert_eq!(ours, theirs);
        assert!(ours.iter().all(|a| a.abs() < 1.0));
        // Stochastic actions differ from the deterministic ones and stay in (-1, 1).
        let sampled = net.act(&obs[..5], false, &mut ChaCha8Rng::seed_from_u64(2));
        assert_eq!(sampled.len(), 3);
        assert_ne!(sampled, ours[..3].to_vec());
        assert!(sampled.iter().all(|a| a.abs() < 1.0));
        let _ = sac.act(&Tensor::zeros([1, 5], (Kind::Float, Device::Cpu)));
        assert_eq!(net.to_safetensors().unwrap(), bytes);
    }

    #[test]
    fn batch_equals_row_by_row_with_the_same_rng() {
        let cfg = small();
        let sac = Sac::new(4, 2, &cfg.sac, &cfg.network, 3).unwrap();
        let net = PolicyNet::from_safetensors(&encode_actor(&sac).unwrap(), &cfg, 4, 2).unwrap();
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
        let a = Sac::new(4, 2, &cfg.sac, &cfg.network, 1).unwrap();
        let b = Sac::new(4, 2, &cfg.sac, &cfg.network, 2).unwrap();
        let net = PolicyNet::from_safetensors(&encode_actor(&a).unwrap(), &cfg, 4, 2).unwrap();
        let obs = [0.1, -0.2, 0.3, 0.4];
        let before = net.act(&obs, true, &mut ChaCha8Rng::seed_from_u64(0));
        net.load(&encode_actor(&b).unwrap()).unwrap();
        let after = net.act(&obs, true, &mut ChaCha8Rng::seed_from_u64(0));
        assert_ne!(before, after);
        let expected = Vec::<f32>::try_from(
            b.act_deterministic(&Tensor::from_slice(&obs).view([1, 4]))
                .view([-1]),
        )
        .unwrap();
        assert_eq!(after, expected);
    }

    #[test]
    fn mismatched_weights_are_rejected_by_name() {
        let cfg = small();
        let sac = Sac::new(5, 3, &cfg.sac, &cfg.network, 0).unwrap();
        let bytes = encode_actor(&sac).unwrap();
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
        let sac = Sac::new(5, 3, &cfg.sac, &cfg.network, 0).unwrap();
        let bytes = encode_actor(&sac).unwrap();
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
}
