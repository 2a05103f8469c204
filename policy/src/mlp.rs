//! The actor network of spec 5.1 (an MLP trunk, a mean head and a log-std head, a tanh-squashed
//! Gaussian on top), its initialisation, and the initialisers it is built from.
//!
//! It lives here rather than in the learner because it is half of the weights contract: the
//! variable names it creates are the tensor names of the format (see the crate docs), and its
//! forward pass is what turns those tensors into actions. The learner trains this very type and
//! actors run it, so the two sides cannot disagree on layout or maths.
//!
//! Weights are stored as Flax kernels, `[fan_in, fan_out]`, so `x · W + b` reads like the spec and
//! the initialisers match Flax's. Every random number comes from a caller-owned seeded
//! [`ChaCha8Rng`], never from libtorch's global generator: a seed fixes a network whatever else
//! runs in the process.
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rfcl_core::config::{MatmulPrecision, NetworkConfig};
use tch::{nn, Device, Kind, Tensor};

/// `[rows, cols]` standard-normal samples from `rng`, as a tensor of `kind` on `device`.
pub fn standard_normal(
    rng: &mut ChaCha8Rng,
    rows: i64,
    cols: i64,
    kind: Kind,
    device: Device,
) -> Tensor {
    let values: Vec<f64> = (0..rows * cols)
        .map(|_| rng.sample(StandardNormal))
        .collect();
    Tensor::from_slice(&values)
        .view([rows, cols])
        .to_kind(kind)
        .to_device(device)
}

/// Orthogonal kernel init (spec 5.1 "orthogonal kernel, gain √2" / heads "gain 1.0"), as Flax's
/// `orthogonal`: a `[fan_in, fan_out]` matrix with orthonormal columns (fan_in ≥ fan_out) or
/// orthonormal rows (fan_in < fan_out), times `gain`. Computed in f64 on the CPU.
pub fn orthogonal(rng: &mut ChaCha8Rng, fan_in: i64, fan_out: i64, gain: f64) -> Tensor {
    let (rows, cols) = if fan_in < fan_out {
        (fan_out, fan_in)
    } else {
        (fan_in, fan_out)
    };
    let a = standard_normal(rng, rows, cols, Kind::Double, Device::Cpu);
    let (q, r) = Tensor::linalg_qr(&a, "reduced");
    // Q · sign(diag R) makes the factorisation unique, hence Q Haar-distributed.
    let q = q * r.diagonal(0, 0, 1).sign().unsqueeze(0);
    let q = if fan_in < fan_out { q.tr() } else { q };
    q * gain
}

/// `x · W + b` in the configured matmul precision. `Bf16` rounds both matmul operands to bfloat16
/// (oneDNN/AMX on CPU, tensor cores on CUDA) and returns the input's kind; the bias add stays in
/// the input's kind. 2-D `x` is a plain GEMM, 3-D a batched one over the leading (member) dim
/// (the learner's critic ensemble uses the same function).
pub fn affine(x: &Tensor, w: &Tensor, b: &Tensor, precision: MatmulPrecision) -> Tensor {
    match precision {
        MatmulPrecision::Fp32 if x.dim() == 2 => b.addmm(x, w),
        MatmulPrecision::Fp32 => b.baddbmm(x, w, 1.0, 1.0),
        MatmulPrecision::Bf16 => {
            let product = x.to_kind(Kind::BFloat16).matmul(&w.to_kind(Kind::BFloat16));
            product.to_kind(x.kind()) + b
        }
    }
}

/// A Dense layer, Flax layout: `w` `[fan_in, fan_out]`, `b` `[fan_out]`, stored as the variables
/// `{name}.kernel` and `{name}.bias` (the format's tensor names).
#[derive(Debug)]
struct Dense {
    w: Tensor,
    b: Tensor,
}

impl Dense {
    fn new(path: &nn::Path, name: &str, w: &Tensor) -> Self {
        let fan_out = w.size()[1];
        Self {
            w: (path / name).var_copy("kernel", w),
            b: (path / name).var_copy(
                "bias",
                &Tensor::zeros([fan_out], (Kind::Double, Device::Cpu)),
            ),
        }
    }

    fn forward(&self, x: &Tensor, precision: MatmulPrecision) -> Tensor {
        affine(x, &self.w, &self.b, precision)
    }

    fn shallow_clone(&self) -> Self {
        Self {
            w: self.w.shallow_clone(),
            b: self.b.shallow_clone(),
        }
    }
}

/// A reparameterised sample of the tanh-squashed Gaussian policy.
#[derive(Debug)]
pub struct PolicySample {
    /// a = tanh(u), in (-1, 1)^A.
    pub action: Tensor,
    /// log π(a|s), summed over action dims: `[B]`.
    pub log_prob: Tensor,
}

/// Spec 5.1: log σ = min + ½(max − min)(tanh(h) + 1), a smooth squash of the log-std head into
/// [min, max] (the reference's −5 + 3.5(tanh(h) + 1)).
pub fn squash_log_std(h: &Tensor, log_std_min: f64, log_std_max: f64) -> Tensor {
    (h.tanh() + 1.0) * (0.5 * (log_std_max - log_std_min)) + log_std_min
}

/// Spec 5.1: log π(a) of the tanh-squashed diagonal Gaussian, summed over the last dim, from the
/// pre-tanh sample u (a = tanh u):
/// Σ_d [log N(u_d; μ_d, σ_d) − log(1 − tanh² u_d)], with the stable form
/// log(1 − tanh² u) = 2(log 2 − u − softplus(−2u)).
pub fn tanh_gaussian_log_prob(u: &Tensor, mean: &Tensor, log_std: &Tensor) -> Tensor {
    let z = (u - mean) * (-log_std).exp();
    let log_normal = z.square() * -0.5 - log_std - 0.5 * (2.0 * std::f64::consts::PI).ln();
    let log_det = ((u * -2.0).softplus() + u - std::f64::consts::LN_2) * 2.0;
    (log_normal + log_det).sum_dim_intlist(-1, false, None)
}

/// The actor of spec 5.1: L × [Dense → ReLU] (`network.actor_features`), then a mean head and a
/// log-std head.
#[derive(Debug)]
pub struct Actor {
    trunk: Vec<Dense>,
    mean: Dense,
    log_std: Dense,
    log_std_min: f64,
    log_std_max: f64,
    precision: MatmulPrecision,
}

impl Actor {
    /// Creates the variables under `path` (in the var store's kind and device) and initialises
    /// them from `rng`: hidden Dense orthogonal √2, zero bias; both heads orthogonal 1.0, zero
    /// bias (spec 5.1). Draw order: trunk layers in order, then the mean head, then the log-std
    /// head; the learner's agent draws the actor first from its seeded RNG, so
    /// [`PolicyNet::init`](crate::PolicyNet::init) with the run seed gives its initial actor.
    pub fn new(
        path: &nn::Path,
        rng: &mut ChaCha8Rng,
        obs_dim: i64,
        action_dim: i64,
        net: &NetworkConfig,
        precision: MatmulPrecision,
    ) -> Self {
        let mut fan_in = obs_dim;
        let mut trunk = Vec::new();
        for (i, &width) in net.actor_features.iter().enumerate() {
            let width = i64::from(width);
            let w = orthogonal(rng, fan_in, width, 2f64.sqrt());
            trunk.push(Dense::new(path, &format!("trunk{i}"), &w));
            fan_in = width;
        }
        let mean = Dense::new(path, "mean", &orthogonal(rng, fan_in, action_dim, 1.0));
        let log_std = Dense::new(path, "log_std", &orthogonal(rng, fan_in, action_dim, 1.0));
        Self {
            trunk,
            mean,
            log_std,
            log_std_min: net.log_std_min,
            log_std_max: net.log_std_max,
            precision,
        }
    }

    /// The same actor on the same parameter tensors (no copy): a handle that another thread can
    /// own (tensors are `Send`, not `Sync`).
    pub fn shallow_clone(&self) -> Self {
        Self {
            trunk: self.trunk.iter().map(Dense::shallow_clone).collect(),
            mean: self.mean.shallow_clone(),
            log_std: self.log_std.shallow_clone(),
            log_std_min: self.log_std_min,
            log_std_max: self.log_std_max,
            precision: self.precision,
        }
    }

    /// (μ, log σ) of the pre-tanh Gaussian π(·|obs), each `[B, A]`.
    pub fn gaussian(&self, obs: &Tensor) -> (Tensor, Tensor) {
        let mut h = obs.shallow_clone();
        for layer in &self.trunk {
            // In place: the fresh matmul output is not needed by autograd.
            h = layer.forward(&h, self.precision).relu_();
        }
        let mean = self.mean.forward(&h, self.precision);
        let log_std = squash_log_std(
            &self.log_std.forward(&h, self.precision),
            self.log_std_min,
            self.log_std_max,
        );
        (mean, log_std)
    }

    /// A reparameterised sample a = tanh(μ + σ·ε) and its log-probability, for caller-drawn
    /// noise ε ~ N(0, I) of shape `[B, A]`.
    pub fn sample(&self, obs: &Tensor, noise: &Tensor) -> PolicySample {
        let (mean, log_std) = self.gaussian(obs);
        let u = &mean + log_std.exp() * noise;
        let log_prob = tanh_gaussian_log_prob(&u, &mean, &log_std);
        PolicySample {
            action: u.tanh(),
            log_prob,
        }
    }

    /// The deterministic (evaluation) action tanh(μ) (spec 5.1, 5.7).
    pub fn deterministic(&self, obs: &Tensor) -> Tensor {
        self.gaussian(obs).0.tanh()
    }
}
