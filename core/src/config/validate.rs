//! Range checks and cross-option rules of a [`RunConfig`]. Each error names the dotted key, the
//! allowed range or rule and the value found; rules that come from the spec cite its section.
use std::fmt::{self, Display};
use std::ops::Bound::{self, Excluded, Included, Unbounded};

use super::error::ConfigError;
use super::{
    ForwardConfig, LevelMix, ReverseConfig, RunConfig, ScoreTransform, StagePlan, Suite,
    TrainConfig, TrainMode,
};

/// The range of `eval_env.video_size`: the actors' video encoder takes frames up to 1024 pixels.
pub const MIN_VIDEO_SIZE: u32 = 16;
pub const MAX_VIDEO_SIZE: u32 = 1024;

impl RunConfig {
    /// Checks every value against its allowed range and the rules between options. Returns the
    /// first violation; [`resolve_file`](super::resolve_file) calls this and adds which file set
    /// the key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.validate_run_and_env()?;
        self.validate_sac()?;
        self.validate_network()?;
        self.validate_train()?;
        self.reverse.validate()?;
        self.forward.validate()?;
        self.validate_service()?;
        at_least_opt("learner.threads", self.learner.threads, 1)
    }

    fn validate_run_and_env(&self) -> Result<(), ConfigError> {
        let (env, eval, service) = (&self.env, &self.eval_env, &self.service);
        let plain_name = !self.name.is_empty()
            && !self.name.contains(['/', '\\'])
            && self.name != "."
            && self.name != "..";
        ensure(plain_name, "name", || {
            format!(
                "must be a plain directory name (the run goes to runs/<name>), got {:?}",
                self.name
            )
        })?;
        ensure(!env.env_id.is_empty(), "env.env_id", || {
            "must not be empty".into()
        })?;
        at_least("env.max_episode_steps", env.max_episode_steps, 1)?;
        at_least("env.num_envs", env.num_envs, 1)?;
        ensure(env.num_envs >= service.num_actors, "env.num_envs", || {
            format!(
                "must be >= service.num_actors ({}): every train actor runs at least one env, got {}",
                service.num_actors, env.num_envs
            )
        })?;
        if let Some(mode) = &env.control_mode {
            ensure(!mode.is_empty(), "env.control_mode", || {
                "must not be empty (null = the suite's default)".into()
            })?;
        }
        ensure(
            env.imports.is_empty() || env.suite.takes_imports(),
            "env.imports",
            || {
                "only the gymnasium and maniskill3 suites import modules; the other suites' \
                 envs are built in (give [] or leave it out)"
                    .into()
            },
        )?;
        for module in &env.imports {
            ensure(
                !module.is_empty() && !module.contains(char::is_whitespace),
                "env.imports",
                || format!("'{module}' is not a Python module name"),
            )?;
        }
        if let Some(success) = &env.success {
            ensure(env.suite == Suite::Gymnasium, "env.success", || {
                "only the gymnasium suite takes a success callable; the other suites report \
                 success themselves"
                    .into()
            })?;
            ensure(
                success
                    .split_once(':')
                    .is_some_and(|(m, f)| !m.is_empty() && !f.is_empty()),
                "env.success",
                || format!("expected module:callable, got '{success}'"),
            )?;
        }
        at_least_opt("env.obs_dim", env.obs_dim, 1)?;
        at_least_opt("env.action_dim", env.action_dim, 1)?;
        ensure(
            eval.num_envs >= service.num_eval_actors,
            "eval_env.num_envs",
            || {
                format!(
                "must be >= service.num_eval_actors ({}): every eval actor runs at least one env, got {}",
                service.num_eval_actors, eval.num_envs
            )
            },
        )?;
        at_least_opt("eval_env.max_episode_steps", eval.max_episode_steps, 1)?;
        ensure(
            (MIN_VIDEO_SIZE..=MAX_VIDEO_SIZE).contains(&eval.video_size),
            "eval_env.video_size",
            || {
                format!(
                    "must be {MIN_VIDEO_SIZE}-{MAX_VIDEO_SIZE} pixels, got {}",
                    eval.video_size
                )
            },
        )?;
        let levels = u64::from(self.forward.num_seeds);
        ensure(eval.seed_offset >= levels, "eval_env.seed_offset", || {
            format!(
                "must be >= forward.num_seeds ({levels}) so that eval seeds are not curriculum levels \
                 (docs/ALGORITHM.md 3.1, 5.7), got {}",
                eval.seed_offset
            )
        })
    }

    fn validate_sac(&self) -> Result<(), ConfigError> {
        let sac = &self.sac;
        at_least("sac.batch_size", sac.batch_size, 2)?;
        ensure(sac.batch_size.is_multiple_of(2), "sac.batch_size", || {
            format!(
                "must be even: every minibatch is half online, half offline (docs/ALGORITHM.md 5.2), got {}",
                sac.batch_size
            )
        })?;
        let envs = u64::from(self.env.num_envs);
        ensure(
            sac.replay_buffer_capacity >= envs,
            "sac.replay_buffer_capacity",
            || {
                format!(
                "must be >= env.num_envs ({envs}): the buffer is a ring per env (docs/ALGORITHM.md 5.5), got {}",
                sac.replay_buffer_capacity
            )
            },
        )?;
        at_least("sac.steps_per_env", sac.steps_per_env, 1)?;
        at_least("sac.actor_update_freq", sac.actor_update_freq, 1)?;
        at_least("sac.grad_updates_per_step", sac.grad_updates_per_step, 1)?;
        ensure(
            sac.grad_updates_per_step
                .is_multiple_of(sac.actor_update_freq),
            "sac.grad_updates_per_step",
            || {
                format!(
                    "must be a multiple of sac.actor_update_freq ({}) (docs/ALGORITHM.md 5.2), got {}",
                    sac.actor_update_freq, sac.grad_updates_per_step
                )
            },
        )?;
        at_least("sac.critic_ensemble", sac.critic_ensemble, 1)?;
        at_least("sac.num_min_qs", sac.num_min_qs, 1)?;
        ensure(sac.num_min_qs <= sac.target_pool, "sac.num_min_qs", || {
            format!(
                "must be <= sac.target_pool ({}): the target draws that many members without \
                 replacement (docs/ALGORITHM.md 5.3), got {}",
                sac.target_pool, sac.num_min_qs
            )
        })?;
        ensure(
            sac.target_pool <= sac.critic_ensemble,
            "sac.target_pool",
            || {
                format!(
                "must be <= sac.critic_ensemble ({}): the pool is members 0..target_pool-1 (docs/ALGORITHM.md 5.1), \
                 got {}",
                sac.critic_ensemble, sac.target_pool
            )
            },
        )?;
        within("sac.discount", sac.discount, UNIT)?;
        within("sac.tau", sac.tau, SHARE)?;
        within("sac.initial_temperature", sac.initial_temperature, POSITIVE)?;
        within_opt("sac.target_entropy", sac.target_entropy, REAL)?;
        within("sac.actor_lr", sac.actor_lr, POSITIVE)?;
        within("sac.critic_lr", sac.critic_lr, POSITIVE)?;
        within("sac.temp_lr", sac.temp_lr, POSITIVE)?;
        within(
            "sac.adam_beta1",
            sac.adam_beta1,
            Interval(Included(0.0), Excluded(1.0)),
        )?;
        within(
            "sac.adam_beta2",
            sac.adam_beta2,
            Interval(Included(0.0), Excluded(1.0)),
        )?;
        within("sac.adam_eps", sac.adam_eps, POSITIVE)?;
        at_least("sac.eval_freq", sac.eval_freq, 1)?;
        at_least("sac.eval_steps", sac.eval_steps, 1)?;
        at_least("sac.log_freq", sac.log_freq, 1)?;
        at_least("sac.save_freq", sac.save_freq, 1)?;
        within("sac.save_every_s", sac.save_every_s, POSITIVE)
    }

    fn validate_network(&self) -> Result<(), ConfigError> {
        let network = &self.network;
        for (key, features) in [
            ("network.actor_features", &network.actor_features),
            ("network.critic_features", &network.critic_features),
        ] {
            ensure(!features.is_empty() && !features.contains(&0), key, || {
                format!("must be a non-empty list of layer widths >= 1, got {features:?}")
            })?;
        }
        within("network.layer_norm_eps", network.layer_norm_eps, POSITIVE)?;
        within("network.log_std_min", network.log_std_min, REAL)?;
        within("network.log_std_max", network.log_std_max, REAL)?;
        ensure(
            network.log_std_min < network.log_std_max,
            "network.log_std_max",
            || {
                format!(
                    "must be > network.log_std_min ({}), got {}",
                    network.log_std_min, network.log_std_max
                )
            },
        )
    }

    fn validate_train(&self) -> Result<(), ConfigError> {
        let train = &self.train;
        at_least("train.steps", train.steps, 1)?;
        if let Some(path) = &train.dataset_path {
            ensure(!path.is_empty(), "train.dataset_path", || {
                "must not be empty (null = no dataset)".into()
            })?;
        }
        at_least("train.num_demos", train.num_demos, 1)?;
        if let Some(scale) = train.data_action_scale {
            within("train.data_action_scale", scale, POSITIVE)?;
            ensure(
                train.train_on_demo_actions,
                "train.data_action_scale",
                || {
                    "cannot be combined with train.train_on_demo_actions: false (docs/ALGORITHM.md 6.3)".into()
                },
            )?;
        }
        train.stage_plan()?;
        // The reference's two other stage-1 eval modes are not implemented: refused rather than
        // accepted and ignored, so no run measures something else than it says.
        ensure(
            train.use_orig_env_for_eval,
            "train.use_orig_env_for_eval",
            || {
                "false (evals from demo states mirroring the curriculum) is not supported by rfcl; \
             evaluations always run on the true task distribution (docs/ALGORITHM.md 2.9)"
                    .into()
            },
        )?;
        ensure(
            !train.eval_start_of_demos,
            "train.eval_start_of_demos",
            || {
                "true (evals from demo state 0) is not supported by rfcl; evaluations always run on \
             the true task distribution (docs/ALGORITHM.md 2.9)"
                .into()
            },
        )?;
        ensure(
            !(train.load_as_online_buffer && train.load_as_offline_buffer),
            "train.load_as_online_buffer",
            || {
                "cannot be combined with train.load_as_offline_buffer: true; the stage-1 buffer becomes \
                 either stage 2's offline or its online buffer (docs/ALGORITHM.md 4.2)"
                    .into()
            },
        )
    }

    fn validate_service(&self) -> Result<(), ConfigError> {
        let service = &self.service;
        at_least("service.num_actors", service.num_actors, 1)?;
        within("service.lease_timeout_s", service.lease_timeout_s, POSITIVE)?;
        at_least(
            "service.snapshot_every_reports",
            service.snapshot_every_reports,
            1,
        )?;
        within(
            "service.snapshot_every_s",
            service.snapshot_every_s,
            POSITIVE,
        )?;
        within(
            "service.forget_actors_after_s",
            service.forget_actors_after_s,
            POSITIVE,
        )?;
        at_least(
            "service.stall_after_env_steps",
            service.stall_after_env_steps,
            1,
        )?;
        at_least("service.transition_batch", service.transition_batch, 1)?;
        let ports = [
            ("service.curriculum_port", service.curriculum_port),
            ("service.learner_port", service.learner_port),
            ("service.dashboard_port", service.dashboard_port),
        ];
        for (i, (key, port)) in ports.iter().enumerate() {
            if let Some((other, _)) = ports[..i].iter().find(|(_, p)| *port != 0 && p == port) {
                return Err(invalid(
                    key,
                    format!("must differ from {other} (both {port}; 0 = any free port)"),
                ));
            }
        }
        within_opt(
            "service.hang_timeout_s",
            service.hang_timeout_s,
            HANG_TIMEOUT_S,
        )?;
        within_opt(
            "service.stop_at_eval_success",
            service.stop_at_eval_success,
            SHARE,
        )?;
        Ok(())
    }
}

impl RunConfig {
    /// The forward curriculum as the run draws it. Under `train.mode: rlpd` every seed is equally
    /// likely (constant scores, no staleness term) and the demos' first states are not levels, so
    /// episodes start from the task's own initial distribution (docs/ALGORITHM.md 4, "RLPD mode").
    pub fn forward_curriculum(&self) -> ForwardConfig {
        match self.train.mode {
            TrainMode::Rfcl => self.forward.clone(),
            TrainMode::Rlpd => ForwardConfig {
                score_transform: ScoreTransform::Constant,
                staleness_transform: ScoreTransform::Constant,
                staleness_coef: 0.0,
                mix: LevelMix::Reference,
                include_demo_starts: false,
                ..self.forward.clone()
            },
        }
    }
}

impl TrainConfig {
    /// `train.stage_1_only` and `train.stage_2_only` as the one choice they encode; both set is
    /// an error naming the key. [`RunConfig::validate`] applies it; the curriculum's stage machine
    /// starts from the plan it returns, so the rule lives here only.
    pub fn stage_plan(&self) -> Result<StagePlan, ConfigError> {
        if self.mode == TrainMode::Rlpd {
            return match self.stage_1_only {
                // RLPD has no reverse curriculum: it is the forward stage with uniform seeds.
                false => Ok(StagePlan::ForwardOnly),
                true => Err(invalid(
                    "train.stage_1_only",
                    "cannot be combined with train.mode: rlpd (RLPD has no stage 1)".into(),
                )),
            };
        }
        match (self.stage_1_only, self.stage_2_only) {
            (false, false) => Ok(StagePlan::Both),
            (true, false) => Ok(StagePlan::ReverseOnly),
            (false, true) => Ok(StagePlan::ForwardOnly),
            (true, true) => Err(invalid(
                "train.stage_2_only",
                "cannot be combined with train.stage_1_only: true".into(),
            )),
        }
    }
}

impl ReverseConfig {
    /// The rules of the `reverse` section on their own. [`RunConfig::validate`] applies them to
    /// every resolved config; the reverse curriculum applies them to sections built in code, so
    /// both hold a config to the same rule.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let probs = &self.geometric_probs;
        ensure(!probs.is_empty(), "reverse.geometric_probs", || {
            "must not be empty".into()
        })?;
        for p in probs {
            within("reverse.geometric_probs", *p, UNIT)?;
        }
        let sum: f64 = probs.iter().sum();
        ensure((sum - 1.0).abs() <= 1e-9, "reverse.geometric_probs", || {
            format!("must sum to 1 (docs/ALGORITHM.md 2.3), got {probs:?} summing to {sum}")
        })?;
        at_least("reverse.reverse_step_size", self.reverse_step_size, 1)?;
        at_least("reverse.per_demo_buffer_size", self.per_demo_buffer_size, 1)?;
        within(
            "reverse.demo_horizon_to_max_steps_ratio",
            self.demo_horizon_to_max_steps_ratio,
            REAL,
        )?;
        within("reverse.solved_demo_weight", self.solved_demo_weight, SHARE)?;
        within(
            "reverse.solved_frac_threshold",
            self.solved_frac_threshold,
            UNIT,
        )?;
        within(
            "reverse.global_success_threshold",
            self.global_success_threshold,
            UNIT,
        )?;
        at_least(
            "reverse.max_trailing_success_states",
            self.max_trailing_success_states,
            1,
        )
    }
}

impl ForwardConfig {
    /// The rules of the `forward` section on their own, held to the same rule as
    /// [`ReverseConfig::validate`]: resolved configs and sections built in code alike.
    pub fn validate(&self) -> Result<(), ConfigError> {
        at_least("forward.num_seeds", self.num_seeds, 1)?;
        within(
            "forward.score_temperature",
            self.score_temperature,
            POSITIVE,
        )?;
        within(
            "forward.staleness_temperature",
            self.staleness_temperature,
            POSITIVE,
        )?;
        within("forward.staleness_coef", self.staleness_coef, UNIT)?;
        at_least("forward.returns_buffer_size", self.returns_buffer_size, 1)?;
        at_least("forward.score_window", self.score_window, 1)?;
        ensure(
            self.score_window <= self.returns_buffer_size,
            "forward.score_window",
            || {
                format!(
                    "must be <= forward.returns_buffer_size ({}), got {}",
                    self.returns_buffer_size, self.score_window
                )
            },
        )?;
        within("forward.score_threshold", self.score_threshold, UNIT)?;
        within("forward.initial_score", self.initial_score, REAL)
    }
}

/// A real interval; NaN and infinities are never inside.
#[derive(Clone, Copy)]
struct Interval(Bound<f64>, Bound<f64>);

const UNIT: Interval = Interval(Included(0.0), Included(1.0));
const POSITIVE: Interval = Interval(Excluded(0.0), Unbounded);
const REAL: Interval = Interval(Unbounded, Unbounded);
/// (0, 1]: a share that must not be zero.
const SHARE: Interval = Interval(Excluded(0.0), Included(1.0));
/// `service.hang_timeout_s`: 5 s to a day.
const HANG_TIMEOUT_S: Interval = Interval(Included(5.0), Included(86_400.0));

impl Interval {
    fn contains(self, x: f64) -> bool {
        let above = match self.0 {
            Included(lo) => x >= lo,
            Excluded(lo) => x > lo,
            Unbounded => true,
        };
        let below = match self.1 {
            Included(hi) => x <= hi,
            Excluded(hi) => x < hi,
            Unbounded => true,
        };
        x.is_finite() && above && below
    }
}

impl Display for Interval {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (self.0, self.1) {
            (Unbounded, Unbounded) => write!(f, "a finite number"),
            (Excluded(lo), Unbounded) => write!(f, "> {lo}"),
            (Included(lo), Unbounded) => write!(f, ">= {lo}"),
            (lo, hi) => {
                match lo {
                    Included(lo) => write!(f, "in [{lo}, ")?,
                    Excluded(lo) => write!(f, "in ({lo}, ")?,
                    Unbounded => write!(f, "in (-inf, ")?,
                }
                match hi {
                    Included(hi) => write!(f, "{hi}]"),
                    Excluded(hi) => write!(f, "{hi})"),
                    Unbounded => write!(f, "inf)"),
                }
            }
        }
    }
}

fn invalid(key: &str, message: String) -> ConfigError {
    ConfigError::Invalid {
        origin: None,
        key: key.to_owned(),
        message,
    }
}

fn ensure(ok: bool, key: &str, message: impl FnOnce() -> String) -> Result<(), ConfigError> {
    if ok {
        Ok(())
    } else {
        Err(invalid(key, message()))
    }
}

fn within(key: &str, value: f64, range: Interval) -> Result<(), ConfigError> {
    ensure(range.contains(value), key, || {
        format!("must be {range}, got {value}")
    })
}

fn within_opt(key: &str, value: Option<f64>, range: Interval) -> Result<(), ConfigError> {
    value.map_or(Ok(()), |v| within(key, v, range))
}

fn at_least<T: PartialOrd + Display>(key: &str, value: T, min: T) -> Result<(), ConfigError> {
    ensure(value >= min, key, || {
        format!("must be >= {min}, got {value}")
    })
}

fn at_least_opt<T: PartialOrd + Display>(
    key: &str,
    value: Option<T>,
    min: T,
) -> Result<(), ConfigError> {
    value.map_or(Ok(()), |value| at_least(key, value, min))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intervals_print_in_the_usual_notation_and_reject_non_finite_values() {
        assert_eq!(UNIT.to_string(), "in [0, 1]");
        assert_eq!(POSITIVE.to_string(), "> 0");
        assert_eq!(
            Interval(Excluded(0.0), Included(1.0)).to_string(),
            "in (0, 1]"
        );
        assert_eq!(REAL.to_string(), "a finite number");
        assert!(POSITIVE.contains(1e-12));
        assert!(!POSITIVE.contains(0.0));
        assert!(!POSITIVE.contains(f64::INFINITY));
        assert!(!REAL.contains(f64::NAN));
        assert!(UNIT.contains(1.0) && !Interval(Included(0.0), Excluded(1.0)).contains(1.0));
    }

    #[test]
    fn the_default_config_is_valid() {
        RunConfig::default().validate().unwrap();
    }

    #[test]
    fn learner_threads_must_be_at_least_one() {
        let mut cfg = RunConfig::default();
        cfg.learner.threads = Some(0);
        let err = cfg.validate().unwrap_err().to_string();
        assert!(
            err.contains("learner.threads") && err.contains(">= 1"),
            "{err}"
        );
        cfg.learner.threads = Some(1);
        cfg.validate().unwrap();
    }
}
