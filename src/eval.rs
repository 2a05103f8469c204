//! `rfcl eval RUN_DIR`: the run's exported policy (`RUN_DIR/policy.safetensors`, written by the
//! learner) on N held-out seeds of the task's true initial-state distribution, with the
//! deterministic policy tanh(μ) (spec 5.7), in this process. With `train.data_action_scale` the
//! env gets a / s, s from `RUN_DIR/policy.json`'s `action_scale` (spec 6.4).
use std::path::Path;

use anyhow::{bail, Context, Result};
use rfcl_actor::policy::PolicyHandle;
use rfcl_actor::rollout::{derive_seed, Rollout, RolloutSettings, StepOutput};
use rfcl_core::lease::{LeaseKind, ResetArgs, ResetLease};
use rfcl_policy::{PolicyDescription, PolicyNet};
use serde::Serialize;

use rfcl_actor::video::{encode_gif, video_name, Recorder};

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
    /// The episodes' videos (`--video`), in order.
    pub videos: Vec<std::path::PathBuf>,
}

impl EvalReport {
    /// For PointMaze: the maze as text with each start cell's success rate as a digit (`9` = 90 %
    /// or more, `0` = under 10 %, `-` = not visited), the goal `G`, walls `#` and hazard walls `X`.
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

/// Runs `episodes` episodes of the run's env from held-out seeds with the run's exported policy;
/// with `video`, writes each episode there as an animated GIF from the env's own renderer.
pub fn eval(run_dir: &Path, episodes: u32, video: Option<&Path>) -> Result<EvalReport> {
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
    // Spec 6.4: with train.data_action_scale the export records s and the env gets a / s.
    let description = run_dir.join("policy.json");
    let action_scale = if description.is_file() {
        PolicyDescription::from_json(&std::fs::read_to_string(&description)?)
            .with_context(|| format!("reading {}", description.display()))?
            .action_scale
    } else if cfg.train.data_action_scale.is_some() {
        bail!(
            "the run sets train.data_action_scale (docs/ALGORITHM.md 6.4) but {} is missing: it records the \
             action scale the policy acts with (the learner exports it with policy.safetensors)",
            description.display()
        );
    } else {
        None
    };
    if let Some(dir) = video {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("creating the video directory {}", dir.display()))?;
    }
    let (obs_dim, action_dim) = rfcl_actor::suite::native_dims(&cfg.env)?;
    let env = rfcl_actor::suite::make_env(
        &cfg.env,
        derive_seed(cfg.seed, EVAL_ACTOR_ID, 0),
        obs_dim,
        action_dim,
        video.map(|_| cfg.eval_env.video_size),
    )?;
    let horizon = cfg
        .eval_env
        .max_episode_steps
        .unwrap_or(cfg.env.max_episode_steps);
    // One observation per forward pass: libtorch's thread pool only spins (OpenMP) on it.
    rfcl_actor::net::configure_inference_threads();
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
    )
    .with_action_scale(action_scale)
    .with_context(|| format!("the action_scale of {}", description.display()))?;
    let first_seed = cfg.eval_env.seed_offset + HELD_OUT_SEED_BASE;
    let mut out = StepOutput::default();
    let (mut at_end, mut once, mut ret, mut len) = (0u32, 0u32, 0.0f64, 0u64);
    let mut outcomes = Vec::with_capacity(episodes as usize);
    let mut videos = Vec::new();
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
        let mut recorder = match video {
            Some(_) => Some(Recorder::new(rollout.render(0)?)),
            None => None,
        };
        loop {
            out.clear();
            rollout.step(Some(&mut policy), &mut out)?;
            let last = !out.finished.is_empty();
            if let Some(rec) = recorder.as_mut() {
                if rec.step(last) {
                    rec.push(rollout.render(0)?);
                }
            }
            if let Some((_, r)) = out.finished.pop() {
                let seed = first_seed + u64::from(k);
                if let (Some(dir), Some(rec)) = (video, recorder.take()) {
                    let label = format!("episode{k:03}");
                    let path =
                        dir.join(video_name(&label, seed, r.success_at_end, r.episode_return));
                    let gif = encode_gif(rec.frames())
                        .with_context(|| format!("encoding {}", path.display()))?;
                    std::fs::write(&path, gif)
                        .with_context(|| format!("writing {}", path.display()))?;
                    videos.push(path);
                }
                outcomes.push((seed, r.success_at_end));
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
        videos,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rfcl_policy::{tensor_names, PolicyShape, FORMAT};

    /// A PointMaze run directory with `train.data_action_scale` set and an exported (untrained)
    /// policy whose `policy.json` records `scale` (none: no `policy.json`).
    fn scaled_run(dir: &Path, scale: Option<Vec<f32>>) {
        std::fs::write(
            dir.join("config.yml"),
            format!(
                "base_config: {}/configs/pointmaze.yml\nname: eval_scale\n\
                 train:\n  data_action_scale: 1.25\nsac:\n  critic_ensemble: 2\n  target_pool: 2\n\
                 network:\n  actor_features: [16, 16]\n  critic_features: [16, 16]\n",
                env!("CARGO_MANIFEST_DIR")
            ),
        )
        .unwrap();
        let cfg = rfcl_core::config::resolve_file(&dir.join("config.yml"), &[]).unwrap();
        let (obs, act) = (
            rfcl_actor::pointmaze::OBS_DIM,
            rfcl_actor::pointmaze::ACTION_DIM,
        );
        let shape = PolicyShape::from_config(&cfg, obs, act);
        let net = PolicyNet::init(shape.clone(), 1).unwrap();
        std::fs::write(
            dir.join("policy.safetensors"),
            net.to_safetensors().unwrap(),
        )
        .unwrap();
        let Some(scale) = scale else { return };
        let desc = PolicyDescription {
            format: FORMAT.into(),
            env_id: cfg.env.env_id.clone(),
            tensors: tensor_names(shape.actor_features.len()),
            shape,
            activation: "relu".into(),
            action_scale: Some(scale),
            policy_version: 1,
            env_steps: 0,
        };
        std::fs::write(dir.join("policy.json"), desc.to_json()).unwrap();
    }

    /// Spec 6.4: `rfcl eval` acts with the exported scale, and refuses a scale that does not fit
    /// the env or a scaled run without its `policy.json`.
    #[test]
    fn eval_applies_the_exported_action_scale() {
        let dir = tempfile::tempdir().unwrap();
        scaled_run(dir.path(), Some(vec![0.8, 1.6]));
        let report = eval(dir.path(), 1, None).unwrap();
        assert_eq!(report.episodes, 1);
        assert_eq!(report.mean_length, rfcl_actor::pointmaze::HORIZON as f64);

        scaled_run(dir.path(), Some(vec![0.8, 1.6, 1.0]));
        let err = format!("{:#}", eval(dir.path(), 1, None).unwrap_err());
        assert!(
            err.contains("action_scale") && err.contains("3 values for 2 action dimensions"),
            "{err}"
        );

        let bare = tempfile::tempdir().unwrap();
        scaled_run(bare.path(), None);
        let err = format!("{:#}", eval(bare.path(), 1, None).unwrap_err());
        assert!(
            err.contains("train.data_action_scale") && err.contains("policy.json is missing"),
            "{err}"
        );
    }

    /// A video from a simulator's own renderer: ManiSkill3 PickCube-v1 (horizon 50) through its
    /// Python worker, at `eval_env.video_size`, with an untrained policy.
    #[test]
    fn eval_writes_a_maniskill3_video_from_its_renderer() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("config.yml"),
            format!(
                "base_config: {}/configs/maniskill3/pick_cube.yml\nname: eval_video_ms3\n\
                 eval_env:\n  video_size: 64\nsac:\n  critic_ensemble: 2\n  target_pool: 2\n\
                 network:\n  actor_features: [16, 16]\n  critic_features: [16, 16]\n",
                env!("CARGO_MANIFEST_DIR")
            ),
        )
        .unwrap();
        let cfg = rfcl_core::config::resolve_file(&dir.path().join("config.yml"), &[]).unwrap();
        let (obs, act) = rfcl_actor::suite::native_dims(&cfg.env).unwrap();
        let net = PolicyNet::init(PolicyShape::from_config(&cfg, obs, act), 1).unwrap();
        std::fs::write(
            dir.path().join("policy.safetensors"),
            net.to_safetensors().unwrap(),
        )
        .unwrap();
        let videos = dir.path().join("videos");
        let report = eval(dir.path(), 1, Some(&videos)).unwrap();
        assert_eq!(report.videos.len(), 1);
        let mut decoder = gif::DecodeOptions::new()
            .read_info(std::fs::File::open(&report.videos[0]).unwrap())
            .unwrap();
        assert_eq!((decoder.width(), decoder.height()), (64, 64));
        let mut frames = 0;
        while decoder.read_next_frame().unwrap().is_some() {
            frames += 1;
        }
        // The reset state, steps 3, 6, ..., 48, and the last, 50.
        assert_eq!(frames, 1 + 16 + 1);
    }

    /// `--video`: one GIF per episode, named by seed, outcome and return, with a frame every
    /// `STEPS_PER_FRAME` steps of the 300-step episode and the last.
    #[test]
    fn eval_writes_a_pointmaze_video_per_episode() {
        let dir = tempfile::tempdir().unwrap();
        scaled_run(dir.path(), Some(vec![0.8, 1.6]));
        let videos = dir.path().join("videos");
        let report = eval(dir.path(), 2, Some(&videos)).unwrap();
        assert_eq!(report.videos.len(), 2);
        let horizon = rfcl_actor::pointmaze::HORIZON as u32;
        let expected_frames = horizon / rfcl_actor::video::STEPS_PER_FRAME + 1;
        for (path, &(seed, success)) in report.videos.iter().zip(&report.outcomes) {
            let name = path.file_name().unwrap().to_str().unwrap();
            let outcome = if success { "success" } else { "failure" };
            assert!(
                name.contains(&format!("_seed{seed}_{outcome}_return")) && name.ends_with(".gif"),
                "{name}"
            );
            let mut decoder = gif::DecodeOptions::new()
                .read_info(std::fs::File::open(path).unwrap())
                .unwrap();
            let mut frames = 0;
            while decoder.read_next_frame().unwrap().is_some() {
                frames += 1;
            }
            assert_eq!(frames, expected_frames as usize, "{name}");
            let side = rfcl_actor::pointmaze::draw::frame_side();
            assert_eq!(decoder.width() as usize, side, "{name}");
        }
    }
}
