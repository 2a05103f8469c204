//! `rfcl eval RUN_DIR`: the run's exported policy (`RUN_DIR/policy.safetensors`, written by the
//! learner) on N held-out seeds of the task's true initial-state distribution, with the
//! deterministic policy tanh(μ) (spec 5.7), in this process.
use std::path::Path;

use anyhow::{bail, Context, Result};
use rfcl_actor::net::{PolicyDescription, PolicyNet};
use rfcl_actor::policy::PolicyHandle;
use rfcl_actor::rollout::{derive_seed, Rollout, RolloutSettings, StepOutput};
use rfcl_core::lease::{LeaseKind, ResetArgs, ResetLease};
use serde::Serialize;

/// Held-out seeds start this far above `eval_env.seed_offset`: the evaluations during training
/// use `seed_offset + 0, 1, 2, ...` and the forward curriculum's levels are `0..num_seeds`.
pub const HELD_OUT_SEED_BASE: u64 = 1 << 40;
/// The actor id of `rfcl eval` in seeds (training actors count up from 0).
const EVAL_ACTOR_ID: u32 = u32::MAX;

/// The outcome of `rfcl eval`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EvalReport {
    pub env_id: String,
    pub episodes: u32,
    pub first_seed: u64,
    pub success_at_end: f64,
    pub success_once: f64,
    pub mean_return: f64,
    pub mean_length: f64,
    /// `(seed, success at the end)` of every episode, in order.
    pub outcomes: Vec<(u64, bool)>,
}

impl EvalReport {
    /// For PointMaze: the maze as text with each start cell's success rate as a digit (`9` = 90 %
    /// or more, `0` = under 10 %, `-` = not visited), the goal `G` and walls `#`.
    pub fn pointmaze_map(&self) -> String {
        let maze = rfcl_core::maze::maze();
        let mut per_cell = std::collections::BTreeMap::<rfcl_core::maze::Cell, (u32, u32)>::new();
        for &(seed, success) in &self.outcomes {
            let c = per_cell.entry(maze.seed_cell(seed)).or_default();
            c.0 += 1;
            c.1 += u32::from(success);
        }
        let mut text = String::new();
        for (r, line) in rfcl_core::maze::MAP.lines().enumerate() {
            for (c, ch) in line.chars().enumerate() {
                text.push(match (ch, per_cell.get(&(r, c))) {
                    ('.', Some(&(n, ok))) => {
                        char::from_digit((10 * ok / n.max(1)).min(9), 10).unwrap_or('?')
                    }
                    ('.', None) => '-',
                    (other, _) => other,
                });
            }
            text.push('\n');
        }
        text
    }
}

/// Runs `episodes` episodes of the run's env from held-out seeds with the run's exported policy.
pub fn eval(run_dir: &Path, episodes: u32) -> Result<EvalReport> {
    if episodes == 0 {
        bail!("-n must be at least 1");
    }
    let config = run_dir.join("config.yml");
    if !config.is_file() {
        bail!(
            "{} is not a run directory: it has no config.yml",
            run_dir.display()
        );
    }
    let cfg = rfcl_core::config::resolve_file(&config, &[])?;
    let weights_path = run_dir.join("policy.safetensors");
    let weights = std::fs::read(&weights_path).with_context(|| {
        format!(
            "reading {} (the learner exports it when a run ends)",
            weights_path.display()
        )
    })?;
    let description = run_dir.join("policy.json");
    if description.is_file() {
        let desc = PolicyDescription::from_json(&std::fs::read_to_string(&description)?)
            .with_context(|| format!("reading {}", description.display()))?;
        if desc.action_scale.is_some() {
            bail!(
                "the policy in {} acts with train.data_action_scale (spec 6.4), which rfcl eval \
                 cannot apply yet",
                run_dir.display()
            );
        }
    }
    let (obs_dim, action_dim) = rfcl_actor::suite::native_dims(&cfg.env)?;
    let env = rfcl_actor::suite::make_env(
        &cfg.env,
        derive_seed(cfg.seed, EVAL_ACTOR_ID, 0),
        obs_dim,
        action_dim,
    )?;
    let horizon = cfg
        .eval_env
        .max_episode_steps
        .unwrap_or(cfg.env.max_episode_steps);
    let net = PolicyNet::from_safetensors(&weights, &cfg, env.obs_dim(), env.action_dim())
        .with_context(|| format!("loading {}", weights_path.display()))?;
    let mut policy = PolicyHandle {
        version: 0,
        env_steps: 0,
        policy: Box::new(net),
    };
    let mut rollout = Rollout::new(
        vec![env],
        cfg.seed,
        RolloutSettings {
            actor_id: EVAL_ACTOR_ID,
            num_seed_steps: 0,
            deterministic: true,
        },
    );
    let first_seed = cfg.eval_env.seed_offset + HELD_OUT_SEED_BASE;
    let mut out = StepOutput::default();
    let (mut at_end, mut once, mut ret, mut len) = (0u32, 0u32, 0.0f64, 0u64);
    let mut outcomes = Vec::with_capacity(episodes as usize);
    for k in 0..episodes {
        rollout.begin(
            0,
            ResetLease {
                lease_id: u64::from(k) + 1,
                kind: LeaseKind::Eval,
                demo_id: 0,
                start_index: 0,
                env_state: Vec::new(),
                reset: ResetArgs {
                    seed: Some(first_seed + u64::from(k)),
                    options: serde_json::json!({}),
                },
                time_limit: horizon,
                stage: 1,
                stage_epoch: 0,
                level: 0,
            },
        )?;
        loop {
            out.clear();
            rollout.step(Some(&mut policy), &mut out)?;
            if let Some((_, r)) = out.finished.pop() {
                outcomes.push((first_seed + u64::from(k), r.success_at_end));
                at_end += u32::from(r.success_at_end);
                once += u32::from(r.success_once);
                ret += r.episode_return;
                len += u64::from(r.length);
                break;
            }
        }
    }
    let n = f64::from(episodes);
    Ok(EvalReport {
        env_id: cfg.env.env_id.clone(),
        episodes,
        first_seed,
        success_at_end: f64::from(at_end) / n,
        success_once: f64::from(once) / n,
        mean_return: ret / n,
        mean_length: len as f64 / n,
        outcomes,
    })
}
