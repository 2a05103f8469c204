//! The weights format of the crate docs: encoding an actor var store, loading and validating
//! bytes into one, the shape that rebuilds the network, and the exported `policy.json`.
use std::collections::HashMap;

use rfcl_core::config::{NetworkConfig, RunConfig};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use tch::{nn, Device, Kind, Tensor};
use thiserror::Error;

/// The `format` metadata value of actor weights written by [`encode_vars`].
pub const FORMAT: &str = "rfcl-actor-v1";

/// Why policy weights could not be encoded or loaded. Causes are sources, never repeated in the
/// message, so a chain printed with `{:#}` shows each cause once.
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

    /// A shape that can be built: a `policy.json` comes from outside the process, so its values
    /// are checked here rather than trusted.
    pub(crate) fn check(&self) -> Result<(), PolicyError> {
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

    /// The network options the actor MLP reads (the rest keep their defaults: they configure the
    /// critic).
    pub(crate) fn network(&self) -> NetworkConfig {
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

/// Every variable of an actor var store (the learner's, or a [`crate::PolicyNet`]'s) as `f32`
/// safetensors bytes, sorted by name, with the metadata of the crate docs: the policy weights of
/// one version. Tensors on a GPU are copied to the host.
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
/// Nothing is trusted: the bytes come over the network or from a file.
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
