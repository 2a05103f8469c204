//! SAC with a Q-ensemble (spec 5.2, 5.3): the losses, one function per formula, and the training
//! iteration that applies them in the schedule of spec 5.2.
//!
//! Read top to bottom: the agent and its networks ([`Sac::new`]), [`Sac::train_iteration`] (the
//! whole algorithm), the `update_*` methods (its three steps) with their losses, and below them
//! the spec's formulas as free functions.
//!
//! An update can run the critic ensemble's members on several threads instead of as one batched
//! computation ([`Sac::set_member_threads`]); that execution, and only that, is
//! [`crate::members`]: the maths are the same.
use crate::adam::Adam;
use crate::batch::Batch;
use crate::error::{LearnerError, Result};
use crate::fused;
use crate::members::{sum, MemberThreads};
use crate::nets::{standard_normal, Actor, CriticEnsemble};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::{Backend, NetworkConfig, RunConfig, SacConfig};
use serde::Serialize;
use tch::{nn, Device, Kind, Tensor};

/// The metrics of spec 5.8 for one training iteration: means over its critic updates
/// (`critic_loss`, `q`) and over its actor / temperature updates (the rest).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct UpdateMetrics {
    pub critic_loss: f64,
    /// Mean Q(s, a) over members and rows.
    pub q: f64,
    pub actor_loss: f64,
    /// −mean log π(a|s) of the actor updates.
    pub entropy: f64,
    /// α used by the actor updates.
    pub temp: f64,
    pub temp_loss: f64,
    pub critic_updates: u64,
    pub actor_updates: u64,
}

impl UpdateMetrics {
    /// `(tag, value)` with spec 5.8's tag names.
    pub fn tagged(&self) -> [(&'static str, f64); 6] {
        [
            ("train/critic/critic_loss", self.critic_loss),
            ("train/critic/q", self.q),
            ("train/actor/actor_loss", self.actor_loss),
            ("train/actor/entropy", self.entropy),
            ("train/temp/temp", self.temp),
            ("train/temp/temp_loss", self.temp_loss),
        ]
    }
}

/// Results of one critic update (detached scalars).
#[derive(Debug)]
pub struct CriticStep {
    pub loss: Tensor,
    pub q: Tensor,
}

/// Results of one actor update (detached scalars).
#[derive(Debug)]
pub struct ActorStep {
    pub loss: Tensor,
    /// −mean log π: the H of the temperature loss.
    pub entropy: Tensor,
}

/// Results of one temperature update (detached scalars).
#[derive(Debug)]
pub struct TemperatureStep {
    pub temp: Tensor,
    pub loss: Tensor,
}

/// The agent: actor, critic ensemble, target critic, temperature, their Adam states and the RNG
/// that draws policy noise and target members.
#[derive(Debug)]
pub struct Sac {
    obs_dim: i64,
    action_dim: i64,
    cfg: SacConfig,
    kind: Kind,
    device: Device,
    target_entropy: f64,
    actor_vs: nn::VarStore,
    critic_vs: nn::VarStore,
    target_vs: nn::VarStore,
    temp_vs: nn::VarStore,
    actor: Actor,
    critic: CriticEnsemble,
    target_critic: CriticEnsemble,
    log_alpha: Tensor,
    actor_opt: Adam,
    critic_opt: Adam,
    temp_opt: Adam,
    /// (target, online) critic parameters, matched by name.
    polyak_pairs: Vec<(Tensor, Tensor)>,
    rng: ChaCha8Rng,
    /// How the critic ensemble's members run (one batched computation unless
    /// [`Sac::set_member_threads`] says otherwise).
    member_threads: MemberThreads,
    /// How a critic update takes its gradients on the CPU ([`Sac::set_backend`]).
    backend: Backend,
}

impl Sac {
    /// A freshly initialised agent in f32.
    pub fn new(
        obs_dim: usize,
        action_dim: usize,
        cfg: &SacConfig,
        net: &NetworkConfig,
        seed: u64,
    ) -> Result<Self> {
        Self::with_kind(obs_dim, action_dim, cfg, net, seed, Kind::Float)
    }

    /// A freshly initialised agent whose parameters and maths are in `kind` (f64 for exact tests).
    pub fn with_kind(
        obs_dim: usize,
        action_dim: usize,
        cfg: &SacConfig,
        net: &NetworkConfig,
        seed: u64,
        kind: Kind,
    ) -> Result<Self> {
        check(obs_dim, action_dim, cfg, net)?;
        let device = match cfg.device {
            rfcl_core::config::Device::Cpu => Device::Cpu,
            rfcl_core::config::Device::Cuda if tch::Cuda::is_available() => Device::Cuda(0),
            rfcl_core::config::Device::Cuda => {
                return Err(LearnerError::Config(
                    "sac.device is cuda but libtorch sees no CUDA device".into(),
                ))
            }
        };
        let (obs_dim, action_dim) = (obs_dim as i64, action_dim as i64);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let store = || {
            let mut vs = nn::VarStore::new(device);
            vs.set_kind(kind);
            vs
        };
        let (actor_vs, critic_vs, mut target_vs, temp_vs) = (store(), store(), store(), store());
        let members = i64::from(cfg.critic_ensemble);
        let precision = cfg.matmul_precision;
        let actor = Actor::new(
            &actor_vs.root(),
            &mut rng,
            obs_dim,
            action_dim,
            net,
            precision,
        );
        let critic_in = obs_dim + action_dim;
        let critic = CriticEnsemble::new(
            &critic_vs.root(),
            &mut rng,
            critic_in,
            members,
            net,
            precision,
        );
        // The target's own init is overwritten at once: it starts as an exact copy (spec 5.1).
        let target_critic = CriticEnsemble::new(
            &target_vs.root(),
            &mut rng.clone(),
            critic_in,
            members,
            net,
            precision,
        );
        target_vs.copy(&critic_vs)?;
        target_vs.freeze();
        let log_alpha = temp_vs.root().var_copy(
            "log_alpha",
            &Tensor::from(cfg.initial_temperature.ln()).to_kind(kind),
        );

        let online = critic_vs.variables();
        let polyak_pairs: Vec<(Tensor, Tensor)> = target_vs
            .variables()
            .into_iter()
            .map(|(name, target)| (target, online[&name].shallow_clone()))
            .collect();

        let adam = |vs: &nn::VarStore, lr: f64| {
            Adam::new(vs, lr, cfg.adam_beta1, cfg.adam_beta2, cfg.adam_eps)
        };
        Ok(Self {
            obs_dim,
            action_dim,
            cfg: cfg.clone(),
            kind,
            device,
            target_entropy: cfg.target_entropy.unwrap_or(-(action_dim as f64) / 2.0),
            actor_opt: adam(&actor_vs, cfg.actor_lr),
            critic_opt: adam(&critic_vs, cfg.critic_lr),
            temp_opt: adam(&temp_vs, cfg.temp_lr),
            actor_vs,
            critic_vs,
            target_vs,
            temp_vs,
            actor,
            critic,
            target_critic,
            log_alpha,
            polyak_pairs,
            rng,
            member_threads: MemberThreads::SERIAL,
            backend: Backend::default(),
        })
    }

    /// One training iteration (spec 5.2) on a prepared batch of G·B rows, already interleaved
    /// online/offline and in minibatch order (see `Replay::sample`): R = G/F rounds of F critic
    /// updates, each followed by a Polyak step, then one actor and one temperature update on the
    /// round's last minibatch.
    pub fn train_iteration(&mut self, batch: &Batch) -> Result<UpdateMetrics> {
        let g = i64::from(self.cfg.grad_updates_per_step);
        let f = i64::from(self.cfg.actor_update_freq);
        let b = i64::from(self.cfg.batch_size);
        if batch.rows() != g * b {
            return Err(LearnerError::Shape(format!(
                "a training iteration takes G·B = {g}·{b} = {} rows, got {}",
                g * b,
                batch.rows()
            )));
        }
        let zero = || Tensor::zeros([], (self.kind, self.device));
        let (mut critic_loss, mut q) = (zero(), zero());
        let (mut actor_loss, mut entropy, mut temp, mut temp_loss) =
            (zero(), zero(), zero(), zero());
        for round in 0..g / f {
            let mut last = None;
            for k in 0..f {
                let minibatch = batch.minibatch(round * f + k, b)?;
                let step = self.update_critic(&minibatch);
                critic_loss += step.loss;
                q += step.q;
                last = Some(minibatch);
            }
            let last = last.expect("F >= 1 (validated)");
            let actor = self.update_actor(&last.obs);
            let temperature = self.update_temperature(&actor.entropy);
            actor_loss += actor.loss;
            entropy += actor.entropy;
            temp += temperature.temp;
            temp_loss += temperature.loss;
        }
        let (g_f, r_f) = (g as f64, (g / f) as f64);
        Ok(UpdateMetrics {
            critic_loss: critic_loss.double_value(&[]) / g_f,
            q: q.double_value(&[]) / g_f,
            actor_loss: actor_loss.double_value(&[]) / r_f,
            entropy: entropy.double_value(&[]) / r_f,
            temp: temp.double_value(&[]) / r_f,
            temp_loss: temp_loss.double_value(&[]) / r_f,
            critic_updates: g as u64,
            actor_updates: (g / f) as u64,
        })
    }

    /// One critic update (spec 5.3 "Critic") followed by the Polyak target step (spec 5.2 3.1),
    /// spread over the member threads (see [`crate::members`]).
    pub fn update_critic(&mut self, minibatch: &Batch) -> CriticStep {
        let members = draw_target_members(
            &mut self.rng,
            self.cfg.target_pool as usize,
            self.cfg.num_min_qs as usize,
        );
        let noise = self.policy_noise(minibatch.rows());
        let target = self.critic_target(minibatch, &members, &noise);
        let step = self.critic_opt.begin_step();
        self.member_threads.critic_update(
            self.backend,
            &self.critic,
            (&self.critic_opt, step),
            (&self.polyak_pairs, self.cfg.tau),
            minibatch,
            &target,
        )
    }

    /// The critic loss for given target members and policy noise at s′: (loss, Q `[E, B]`).
    pub fn critic_loss(
        &self,
        minibatch: &Batch,
        members: &[i64],
        noise: &Tensor,
    ) -> (Tensor, Tensor) {
        let target = self.critic_target(minibatch, members, noise);
        let q = self.critic.forward(&minibatch.obs, &minibatch.action);
        (mean_squared_td_error(&q, &target), q)
    }

    /// The regression target y `[B]` of spec 5.3 "Critic" (no autograd history), for given target
    /// members and policy noise at s′. With member threads, each thread computes the target of a
    /// range of the minibatch's rows.
    pub fn critic_target(&self, minibatch: &Batch, members: &[i64], noise: &Tensor) -> Tensor {
        let target_critic = self.target_critic.select(members);
        let alpha = self.cfg.backup_entropy.then(|| self.alpha());
        let job = |start: i64, len: i64| TargetRows {
            actor: self.actor.shallow_clone(),
            target_critic: target_critic.shallow_clone(),
            alpha: alpha.as_ref().map(Tensor::shallow_clone),
            next_obs: minibatch.next_obs.narrow(0, start, len),
            noise: noise.narrow(0, start, len),
            reward: minibatch.reward.narrow(0, start, len),
            mask: minibatch.mask.narrow(0, start, len),
            discount: self.cfg.discount,
        };
        let parts = self
            .member_threads
            .by_rows(minibatch.rows(), job, TargetRows::target);
        Tensor::cat(&parts, 0)
    }

    /// One actor update (spec 5.3 "Actor"): gradients reach the actor only. With member threads,
    /// each thread takes the loss and gradients of a range of the rows, which add up to the
    /// minibatch's.
    pub fn update_actor(&mut self, obs: &Tensor) -> ActorStep {
        let rows = obs.size()[0];
        let noise = self.policy_noise(rows);
        let critic = self.critic.shard(0, self.critic.members(), false);
        let alpha = self.alpha();
        let params = self.actor_opt.params();
        let job = |start: i64, len: i64| ActorRows {
            backend: self.backend,
            actor: self.actor.shallow_clone(),
            params: params.iter().map(|p| p.shallow_clone()).collect(),
            critic: critic.shallow_clone(),
            alpha: alpha.shallow_clone(),
            obs: obs.narrow(0, start, len),
            noise: noise.narrow(0, start, len),
            weight: len as f64 / rows as f64,
        };
        let parts = self.member_threads.by_rows(rows, job, ActorRows::run);
        let grads = (0..params.len())
            .map(|i| sum(parts.iter().map(|p| &p.grads[i])))
            .collect();
        self.actor_opt.step(grads);
        ActorStep {
            loss: sum(parts.iter().map(|p| &p.loss)),
            entropy: -sum(parts.iter().map(|p| &p.log_prob_sum)) / rows as f64,
        }
    }

    /// The actor loss for given policy noise: (loss, log π `[B]`).
    pub fn actor_loss(&self, obs: &Tensor, noise: &Tensor) -> (Tensor, Tensor) {
        let pi = self.actor.sample(obs, noise);
        let q = self.critic.forward(obs, &pi.action);
        (policy_loss(&self.alpha(), &pi.log_prob, &q), pi.log_prob)
    }

    /// One temperature update (spec 5.3 "Temperature"); α stays put without `learnable_temp`.
    pub fn update_temperature(&mut self, entropy: &Tensor) -> TemperatureStep {
        let temp = self.alpha();
        let loss = temperature_loss(&self.log_alpha, entropy, self.target_entropy);
        if self.cfg.learnable_temp {
            self.temp_opt.minimize(&loss);
        }
        TemperatureStep {
            temp,
            loss: loss.detach(),
        }
    }

    /// α = exp(log α), detached: a constant wherever it scales another loss.
    pub fn alpha(&self) -> Tensor {
        self.log_alpha.exp().detach()
    }

    /// ε ~ N(0, I), `[rows, A]`, from the agent's RNG.
    fn policy_noise(&mut self, rows: i64) -> Tensor {
        standard_normal(&mut self.rng, rows, self.action_dim, self.kind, self.device)
    }

    /// Stochastic actions for acting (no autograd history), `[B, A]`.
    pub fn act(&mut self, obs: &Tensor) -> Tensor {
        let noise = self.policy_noise(obs.size()[0]);
        tch::no_grad(|| self.actor.sample(obs, &noise).action)
    }

    /// Deterministic actions tanh(μ) for evaluation (spec 5.7), `[B, A]`.
    pub fn act_deterministic(&self, obs: &Tensor) -> Tensor {
        tch::no_grad(|| self.actor.deterministic(obs))
    }

    /// Docs/ALGORITHM.md 4.1 with `train.load_actor` or `train.load_critic` false: the actor, or
    /// the critic ensemble with its target and the temperature, starts stage 2 from a fresh
    /// initialisation (the one [`Sac::with_kind`] gives for `seed` and `net`) with a fresh Adam
    /// state; the other part and the RNG are kept.
    pub fn reinitialise(
        &mut self,
        actor: bool,
        critic: bool,
        net: &NetworkConfig,
        seed: u64,
    ) -> Result<()> {
        if !actor && !critic {
            return Ok(());
        }
        let fresh = Self::with_kind(
            self.obs_dim as usize,
            self.action_dim as usize,
            &self.cfg,
            net,
            seed,
            self.kind,
        )?;
        let cfg = &self.cfg;
        let adam = |vs: &nn::VarStore, lr: f64| {
            Adam::new(vs, lr, cfg.adam_beta1, cfg.adam_beta2, cfg.adam_eps)
        };
        if actor {
            self.actor_vs.copy(&fresh.actor_vs)?;
            self.actor_opt = adam(&self.actor_vs, cfg.actor_lr);
        }
        if critic {
            // In place: the Polyak pairs and the member shards keep pointing at these tensors.
            self.critic_vs.copy(&fresh.critic_vs)?;
            self.target_vs.copy(&fresh.critic_vs)?;
            self.critic_opt = adam(&self.critic_vs, cfg.critic_lr);
            self.temp_vs.copy(&fresh.temp_vs)?;
            self.temp_opt = adam(&self.temp_vs, cfg.temp_lr);
        }
        Ok(())
    }

    /// Runs the critic ensemble's members on `threads` threads (at most one per member), with
    /// [`crate::members::SHARDS_PER_THREAD`] shards each: same losses, same gradients up to float
    /// summation order, same RNG draws (see [`crate::members`]). CUDA ignores it.
    pub fn set_member_threads(&mut self, threads: usize) {
        let members = self.critic.members() as usize;
        self.member_threads = MemberThreads::per_thread(threads, members, self.device);
    }

    /// [`Sac::set_member_threads`] with an explicit shard count (clamped to 1..=members; at
    /// least one shard per thread), for benchmarks.
    pub fn set_member_parallelism(&mut self, threads: usize, shards: usize) {
        let members = self.critic.members() as usize;
        self.member_threads = MemberThreads::new(threads, shards, members, self.device);
    }

    /// How critic updates take their gradients on the CPU: libtorch's autograd, or the fused
    /// path of [`crate::fused`] (same maths; it falls back to autograd where it does not apply).
    pub fn set_backend(&mut self, backend: Backend) {
        self.backend = backend;
    }

    pub fn backend(&self) -> Backend {
        self.backend
    }

    /// See [`Sac::set_member_threads`].
    pub fn member_threads(&self) -> usize {
        self.member_threads.threads()
    }

    /// See [`Sac::set_member_parallelism`].
    pub fn member_shards(&self) -> usize {
        self.member_threads.shards()
    }

    pub fn actor(&self) -> &Actor {
        &self.actor
    }
    pub fn critic(&self) -> &CriticEnsemble {
        &self.critic
    }
    pub fn target_critic(&self) -> &CriticEnsemble {
        &self.target_critic
    }
    pub fn actor_vars(&self) -> &nn::VarStore {
        &self.actor_vs
    }
    pub fn critic_vars(&self) -> &nn::VarStore {
        &self.critic_vs
    }
    pub fn target_critic_vars(&self) -> &nn::VarStore {
        &self.target_vs
    }
    pub fn temperature_vars(&self) -> &nn::VarStore {
        &self.temp_vs
    }
    pub fn optimizers(&self) -> [(&'static str, &Adam); 3] {
        [
            ("actor", &self.actor_opt),
            ("critic", &self.critic_opt),
            ("temperature", &self.temp_opt),
        ]
    }
    pub fn optimizers_mut(&mut self) -> [(&'static str, &mut Adam); 3] {
        [
            ("actor", &mut self.actor_opt),
            ("critic", &mut self.critic_opt),
            ("temperature", &mut self.temp_opt),
        ]
    }
    /// The RNG that draws policy noise and target members (checkpoint it to resume exactly).
    pub fn rng(&self) -> &ChaCha8Rng {
        &self.rng
    }
    pub fn set_rng(&mut self, rng: ChaCha8Rng) {
        self.rng = rng;
    }
    pub fn target_entropy(&self) -> f64 {
        self.target_entropy
    }
    pub fn obs_dim(&self) -> usize {
        self.obs_dim as usize
    }
    pub fn action_dim(&self) -> usize {
        self.action_dim as usize
    }
    pub fn device(&self) -> Device {
        self.device
    }
    pub fn kind(&self) -> Kind {
        self.kind
    }
    pub fn config(&self) -> &SacConfig {
        &self.cfg
    }
}

/// The inputs of the critic's regression target for a range of a minibatch's rows (see
/// [`Sac::critic_target`]), owned so that a member thread can compute it.
struct TargetRows {
    actor: Actor,
    /// The drawn target members.
    target_critic: CriticEnsemble,
    /// α when the target backs up the entropy term.
    alpha: Option<Tensor>,
    next_obs: Tensor,
    noise: Tensor,
    reward: Tensor,
    mask: Tensor,
    discount: f64,
}

impl TargetRows {
    /// Spec 5.3 "Critic" steps 1-3: y `[rows]`, without autograd history.
    fn target(self) -> Tensor {
        tch::no_grad(|| {
            let next = self.actor.sample(&self.next_obs, &self.noise);
            let next_q = self.target_critic.forward(&self.next_obs, &next.action);
            let mut next_v = next_q.amin(0, false);
            if let Some(alpha) = &self.alpha {
                next_v -= alpha * next.log_prob;
            }
            bellman_target(&self.reward, &self.mask, &next_v, self.discount)
        })
    }
}

/// An actor update's work on a range of the minibatch's rows (see [`Sac::update_actor`]), owned
/// so that a member thread can do it.
struct ActorRows {
    backend: Backend,
    actor: Actor,
    /// The actor's parameters, in its optimiser's order.
    params: Vec<Tensor>,
    /// The critic ensemble, without gradients for its parameters (they reach the actor only).
    critic: CriticEnsemble,
    alpha: Tensor,
    obs: Tensor,
    noise: Tensor,
    /// The range's share of the rows, rows / B.
    weight: f64,
}

struct ActorRowsPart {
    /// The loss of spec 5.3 "Actor" on these rows times their share of the minibatch.
    loss: Tensor,
    /// Σ log π over these rows.
    log_prob_sum: Tensor,
    /// The gradients of `loss` with respect to the actor's parameters.
    grads: Vec<Tensor>,
}

impl ActorRows {
    fn run(self) -> ActorRowsPart {
        let pi = self.actor.sample(&self.obs, &self.noise);
        let fused = match self.backend {
            Backend::Fused => {
                // −weight · mean_b mean_k Q_k: dL/dQ_{k,b} = −weight / (E·B).
                let coefficient =
                    -self.weight / (self.critic.members() * self.obs.size()[0]) as f64;
                fused::critic_action_grad(&self.critic, &self.obs, &pi.action.detach(), coefficient)
            }
            Backend::Libtorch => None,
        };
        let (loss, grads) = match fused {
            // The critic's gradient with respect to the actions is a constant here: the
            // surrogate α·log π·weight + Σ action · dL/daction has the loss's gradients.
            Some((q, action_grad)) => {
                let log_term = (&self.alpha * &pi.log_prob).mean(None) * self.weight;
                let surrogate = log_term + (&pi.action * &action_grad).sum(None);
                let grads = Tensor::run_backward(&[&surrogate], &self.params, false, false);
                (
                    policy_loss(&self.alpha, &pi.log_prob.detach(), &q) * self.weight,
                    grads,
                )
            }
            None => {
                let q = self.critic.forward(&self.obs, &pi.action);
                let loss = policy_loss(&self.alpha, &pi.log_prob, &q) * self.weight;
                let grads = Tensor::run_backward(&[&loss], &self.params, false, false);
                (loss.detach(), grads)
            }
        };
        ActorRowsPart {
            loss,
            log_prob_sum: pi.log_prob.detach().sum(None),
            grads,
        }
    }
}

/// Spec 5.3 "Critic" step 2: `num_min_qs` distinct members drawn uniformly from
/// {0, …, target_pool − 1}; one draw per critic update, shared by the whole minibatch.
pub fn draw_target_members(
    rng: &mut ChaCha8Rng,
    target_pool: usize,
    num_min_qs: usize,
) -> Vec<i64> {
    rand::seq::index::sample(rng, target_pool, num_min_qs)
        .into_iter()
        .map(|i| i as i64)
        .collect()
}

/// Spec 5.3 "Critic" step 3: y = r + γ·mask·V(s′), with V(s′) = min_{k∈I} Q̄_k(s′, a′)
/// (minus α log π(a′|s′) with `backup_entropy`).
pub fn bellman_target(reward: &Tensor, mask: &Tensor, next_v: &Tensor, discount: f64) -> Tensor {
    reward + mask * next_v * discount
}

/// Spec 5.3 "Critic" step 4: mean over all members and rows of (Q_k(s, a) − y)², no ½.
/// `q` is `[E, B]`, `target` `[B]`.
pub fn mean_squared_td_error(q: &Tensor, target: &Tensor) -> Tensor {
    (q - target.unsqueeze(0)).square().mean(None)
}

/// Spec 5.3 "Actor": mean over rows of α·log π(a|s) − mean_k Q_k(s, a), α a constant.
/// `log_prob` is `[B]`, `q` `[E, B]`.
pub fn policy_loss(alpha: &Tensor, log_prob: &Tensor, q: &Tensor) -> Tensor {
    (alpha * log_prob - q.mean_dim(0, false, None)).mean(None)
}

/// Spec 5.3 "Temperature": α·(H − H̄), H = −mean log π from the actor step (a constant),
/// H̄ the target entropy; the gradient goes to log α.
pub fn temperature_loss(log_alpha: &Tensor, entropy: &Tensor, target_entropy: f64) -> Tensor {
    log_alpha.exp() * (entropy.detach() - target_entropy)
}

/// Spec 5.2 3.1: θ̄ ← (1 − τ)·θ̄ + τ·θ for every (target, online) parameter pair, in place.
pub fn polyak_update(pairs: &[(Tensor, Tensor)], tau: f64) {
    tch::no_grad(|| {
        for (target, online) in pairs {
            let _ = target.shallow_clone().lerp_(online, tau);
        }
    });
}

/// Dims that cannot work, and the config rules of [`RunConfig::validate`] (which every loaded
/// config has passed already): an agent can also be built from sections that never went through a
/// config file (benchmarks, tests), and must not start on options that cannot work.
fn check(obs_dim: usize, action_dim: usize, cfg: &SacConfig, net: &NetworkConfig) -> Result<()> {
    if obs_dim == 0 || action_dim == 0 {
        return Err(LearnerError::Config(format!(
            "obs_dim {obs_dim} and action_dim {action_dim} must be positive"
        )));
    }
    let run = RunConfig {
        sac: cfg.clone(),
        network: net.clone(),
        ..RunConfig::default()
    };
    run.validate()
        .map_err(|err| LearnerError::Config(err.to_string()))
}
