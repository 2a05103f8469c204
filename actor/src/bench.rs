//! `rfcl bench actor`: what an actor's machinery costs on top of stepping the same envs with the
//! same policy (the goal: under 5 %).
//!
//! Both loops run K native PointMaze envs with one policy network of the run's config (fresh
//! weights, initialised from the run seed: the cost does not depend on their values), one
//! libtorch thread, in this process:
//!
//! * **bare**: for each env, `policy.act(obs)` then `env.step(action)`, resetting every H steps;
//! * **actor**: what an actor does per step: [`Rollout::step`] (leases, exploration rule, sparse
//!   reward, episode bookkeeping, transitions) plus encoding every transition into the wire record
//!   (`rfcl_core::transition`), with a new lease for every finished episode.
//!
//! The network is the same in both, so the difference is the actor's own overhead. Windows
//! alternate (bare, actor, bare, ...) and the best of each counts, so that load from other
//! processes hits both alike.
use std::time::{Duration, Instant};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::RunConfig;
use rfcl_core::lease::{LeaseKind, ResetArgs, ResetLease};
use rfcl_core::transition::RecordLayout;
use rfcl_policy::{PolicyNet, PolicyShape};
use serde::Serialize;

use crate::env::Env;
use crate::pointmaze::PointMaze;
use crate::policy::PolicyHandle;
use crate::rollout::{Rollout, RolloutSettings, StepOutput};

/// The measurement (`rfcl bench actor` prints it as JSON).
#[derive(Debug, Clone, Serialize)]
pub struct ActorOverhead {
    pub envs: usize,
    pub window_seconds: f64,
    pub windows: u32,
    pub hidden: Vec<u32>,
    /// Env steps per second of the bare loop (best window).
    pub bare_steps_per_s: f64,
    /// Env steps per second through the actor's rollout and encoding (best window).
    pub actor_steps_per_s: f64,
    /// 1 − actor / bare, in percent.
    pub overhead_pct: f64,
}

/// Runs `windows` alternating windows of each loop, `window` long, with `envs` PointMaze envs and
/// the actor network of `cfg`.
pub fn actor_overhead(
    cfg: &RunConfig,
    envs: usize,
    window: Duration,
    windows: u32,
) -> anyhow::Result<ActorOverhead> {
    crate::net::configure_inference_threads();
    let (obs_dim, action_dim) = (crate::pointmaze::OBS_DIM, crate::pointmaze::ACTION_DIM);
    let shape = PolicyShape::from_config(cfg, obs_dim, action_dim);
    let weights = PolicyNet::init(shape, cfg.seed)?.to_safetensors()?;
    let horizon = cfg.env.max_episode_steps;
    let (mut bare_best, mut actor_best) = (0f64, 0f64);
    for _ in 0..windows {
        let net = PolicyNet::from_safetensors(&weights, cfg, obs_dim, action_dim)?;
        bare_best = bare_best.max(bare_loop(&net, envs, horizon, window)?);
        let net = PolicyNet::from_safetensors(&weights, cfg, obs_dim, action_dim)?;
        actor_best = actor_best.max(actor_loop(net, envs, horizon, window, obs_dim, action_dim)?);
    }
    Ok(ActorOverhead {
        envs,
        window_seconds: window.as_secs_f64(),
        windows,
        hidden: cfg.network.actor_features.clone(),
        bare_steps_per_s: bare_best,
        actor_steps_per_s: actor_best,
        overhead_pct: 100.0 * (1.0 - actor_best / bare_best),
    })
}

/// Steps per second of the bare loop.
fn bare_loop(net: &PolicyNet, envs: usize, horizon: u32, window: Duration) -> anyhow::Result<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut pool: Vec<PointMaze> = (0..envs).map(|i| PointMaze::new(i as u64)).collect();
    let mut obs: Vec<Vec<f32>> = Vec::with_capacity(envs);
    for (i, env) in pool.iter_mut().enumerate() {
        obs.push(env.reset_to_seed(Some(i as u64), &serde_json::json!({}))?);
    }
    let (start, mut steps, mut t) = (Instant::now(), 0u64, 0u32);
    while start.elapsed() < window {
        t += 1;
        for (i, env) in pool.iter_mut().enumerate() {
            let action = net.act(&obs[i], false, &mut rng);
            obs[i] = if t % horizon == 0 {
                env.reset_to_seed(Some(u64::from(t) + i as u64), &serde_json::json!({}))?
            } else {
                env.step(&action)?.obs
            };
            steps += 1;
        }
    }
    Ok(steps as f64 / start.elapsed().as_secs_f64())
}

/// Steps per second through [`Rollout`] and the wire encoding.
fn actor_loop(
    net: PolicyNet,
    envs: usize,
    horizon: u32,
    window: Duration,
    obs_dim: usize,
    action_dim: usize,
) -> anyhow::Result<f64> {
    let pool: Vec<Box<dyn Env>> = (0..envs)
        .map(|i| Box::new(PointMaze::new(i as u64)) as Box<dyn Env>)
        .collect();
    let mut rollout = Rollout::new(
        pool,
        0,
        RolloutSettings {
            actor_id: 0,
            num_seed_steps: 0,
            deterministic: false,
        },
    );
    let mut policy = PolicyHandle {
        version: 1,
        env_steps: 1,
        policy: Box::new(net),
    };
    let codec = RecordLayout::new(obs_dim, action_dim);
    let mut wire = Vec::new();
    let mut next_lease = 0u64;
    let lease = |id: u64| ResetLease {
        lease_id: id,
        kind: LeaseKind::Level,
        demo_id: 0,
        start_index: 0,
        env_state: Vec::new(),
        reset: ResetArgs {
            seed: Some(id),
            options: serde_json::json!({}),
        },
        time_limit: horizon,
        stage: 2,
        stage_epoch: 1,
        level: 0,
    };
    let mut out = StepOutput::default();
    let (start, mut steps) = (Instant::now(), 0u64);
    while start.elapsed() < window {
        for env in rollout.idle_envs() {
            next_lease += 1;
            rollout.begin(env, lease(next_lease))?;
        }
        out.clear();
        rollout.step(Some(&mut policy), &mut out)?;
        wire.resize(out.transitions.len() * codec.record_bytes(), 0);
        codec.encode_batch(&out.transitions, &mut wire)?;
        steps += out.transitions.len() as u64;
    }
    Ok(steps as f64 / start.elapsed().as_secs_f64())
}
