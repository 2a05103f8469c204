//! Independent re-implementations for the tests: the spec 5.1 networks and 5.3 losses written as
//! plain f64 loops over weights read out of the var stores, sharing no code with the library.
#![allow(dead_code)]

use rfcl_core::config::{NetworkConfig, SacConfig};
use std::collections::HashMap;
use tch::{nn, Kind, Tensor};

pub fn values(t: &Tensor) -> Vec<f64> {
    Vec::<f64>::try_from(t.detach().to_kind(Kind::Double).flatten(0, -1)).unwrap()
}

pub fn tensor(rows: usize, cols: usize, data: &[f64]) -> Tensor {
    Tensor::from_slice(data).view([rows as i64, cols as i64])
}

/// A small f64 config: 2-layer nets, 4 critics, target min over 2 drawn from 3.
pub fn small_config() -> (SacConfig, NetworkConfig) {
    let sac = SacConfig {
        batch_size: 6,
        grad_updates_per_step: 4,
        actor_update_freq: 2,
        critic_ensemble: 4,
        target_pool: 3,
        num_min_qs: 2,
        discount: 0.9,
        ..SacConfig::default()
    };
    let net = NetworkConfig {
        actor_features: vec![5, 7],
        critic_features: vec![6, 5],
        ..NetworkConfig::default()
    };
    (sac, net)
}

/// Deterministic pseudo-random numbers in [-1, 1] (a tiny LCG, independent of the library).
pub fn pseudo_random(n: usize, seed: u64) -> Vec<f64> {
    let mut state = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (0..n)
        .map(|_| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        })
        .collect()
}

/// A Flax-layout dense layer as flat f64: w[i * out + o].
#[derive(Clone)]
pub struct NaiveDense {
    pub w: Vec<f64>,
    pub b: Vec<f64>,
    pub fan_in: usize,
    pub fan_out: usize,
}

impl NaiveDense {
    pub fn apply(&self, x: &[f64]) -> Vec<f64> {
        (0..self.fan_out)
            .map(|o| {
                self.b[o]
                    + (0..self.fan_in)
                        .map(|i| x[i] * self.w[i * self.fan_out + o])
                        .sum::<f64>()
            })
            .collect()
    }
}

fn vars(vs: &nn::VarStore) -> HashMap<String, Tensor> {
    vs.variables()
}

pub struct NaiveActor {
    pub trunk: Vec<NaiveDense>,
    pub mean: NaiveDense,
    pub log_std: NaiveDense,
    pub log_std_min: f64,
    pub log_std_max: f64,
}

impl NaiveActor {
    pub fn from_vars(vs: &nn::VarStore, net: &NetworkConfig) -> Self {
        let v = vars(vs);
        let dense = |name: &str| {
            let w = &v[&format!("{name}.kernel")];
            let size = w.size();
            NaiveDense {
                w: values(w),
                b: values(&v[&format!("{name}.bias")]),
                fan_in: size[0] as usize,
                fan_out: size[1] as usize,
            }
        };
        Self {
            trunk: (0..net.actor_features.len())
                .map(|i| dense(&format!("trunk{i}")))
                .collect(),
            mean: dense("mean"),
            log_std: dense("log_std"),
            log_std_min: net.log_std_min,
            log_std_max: net.log_std_max,
        }
    }

    /// (μ, log σ) for one observation.
    pub fn gaussian(&self, obs: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let mut h = obs.to_vec();
        for layer in &self.trunk {
            h = layer.apply(&h).into_iter().map(|x| x.max(0.0)).collect();
        }
        let mean = self.mean.apply(&h);
        let log_std = self
            .log_std
            .apply(&h)
            .into_iter()
            .map(|x| {
                self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (x.tanh() + 1.0)
            })
            .collect();
        (mean, log_std)
    }

    /// (a, log π(a)) for one observation and noise row, with the textbook (non-stable) correction
    /// log π = Σ log N(u; μ, σ) − log(1 − tanh² u).
    pub fn sample(&self, obs: &[f64], noise: &[f64]) -> (Vec<f64>, f64) {
        let (mean, log_std) = self.gaussian(obs);
        let mut log_prob = 0.0;
        let mut action = Vec::new();
        for d in 0..mean.len() {
            let sigma = log_std[d].exp();
            let u = mean[d] + sigma * noise[d];
            let z = (u - mean[d]) / sigma;
            log_prob += -0.5 * z * z - sigma.ln() - 0.5 * (2.0 * std::f64::consts::PI).ln();
            log_prob -= (1.0 - u.tanh().powi(2)).ln();
            action.push(u.tanh());
        }
        (action, log_prob)
    }
}

/// One critic member as plain layers.
pub struct NaiveCritic {
    pub layers: Vec<NaiveDense>,
    /// (scale, bias) per hidden layer, empty without LayerNorm.
    pub norms: Vec<(Vec<f64>, Vec<f64>)>,
    pub output: NaiveDense,
    pub eps: f64,
}

impl NaiveCritic {
    /// Member `e` of the ensemble stored in `vs`.
    pub fn member(vs: &nn::VarStore, net: &NetworkConfig, e: usize) -> Self {
        let v = vars(vs);
        let stacked = |name: &str| {
            let w = &v[&format!("{name}.kernel")];
            let size = w.size();
            let (fi, fo) = (size[1] as usize, size[2] as usize);
            NaiveDense {
                w: values(w)[e * fi * fo..(e + 1) * fi * fo].to_vec(),
                b: values(&v[&format!("{name}.bias")])[e * fo..(e + 1) * fo].to_vec(),
                fan_in: fi,
                fan_out: fo,
            }
        };
        let layers = (0..net.critic_features.len())
            .map(|l| stacked(&format!("hidden{l}")))
            .collect();
        let norms = if net.critic_layer_norm {
            net.critic_features
                .iter()
                .enumerate()
                .map(|(i, &width)| {
                    let width = width as usize;
                    let part = |t: &str| {
                        values(&v[&format!("norm{i}.{t}")])[e * width..(e + 1) * width].to_vec()
                    };
                    (part("scale"), part("bias"))
                })
                .collect()
        } else {
            Vec::new()
        };
        Self {
            layers,
            norms,
            output: stacked("output"),
            eps: net.layer_norm_eps,
        }
    }

    pub fn q(&self, obs: &[f64], action: &[f64]) -> f64 {
        let mut h: Vec<f64> = obs.iter().chain(action).copied().collect();
        for (l, layer) in self.layers.iter().enumerate() {
            h = layer.apply(&h);
            if let Some((scale, bias)) = self.norms.get(l) {
                let n = h.len() as f64;
                let mean = h.iter().sum::<f64>() / n;
                let var = h.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
                h = h
                    .iter()
                    .enumerate()
                    .map(|(j, x)| (x - mean) / (var + self.eps).sqrt() * scale[j] + bias[j])
                    .collect();
            }
            h = h.into_iter().map(|x| x.max(0.0)).collect();
        }
        self.output.apply(&h)[0]
    }
}

pub fn naive_critics(vs: &nn::VarStore, net: &NetworkConfig, members: usize) -> Vec<NaiveCritic> {
    (0..members)
        .map(|e| NaiveCritic::member(vs, net, e))
        .collect()
}
