//! `RunConfig::validate`: every range and rule rejects a bad value with the key and the reason,
//! and accepts the edges of each range.
use rfcl_core::config::{ConfigError, RunConfig};

type Edit = fn(&mut RunConfig);

/// Applies `edit` to the default config and returns the validation error.
fn rejected(edit: Edit) -> ConfigError {
    let mut config = RunConfig::default();
    edit(&mut config);
    config
        .validate()
        .expect_err("the edit should make the config invalid")
}

fn accepted(edit: Edit) -> bool {
    let mut config = RunConfig::default();
    edit(&mut config);
    config.validate().is_ok()
}

#[test]
fn out_of_range_values_are_rejected_with_key_and_range() {
    let cases: &[(Edit, &str, &str)] = &[
        (|c| c.sac.tau = 0.0, "sac.tau", "must be in (0, 1], got 0"),
        (|c| c.sac.tau = 1.5, "sac.tau", "must be in (0, 1], got 1.5"),
        (
            |c| c.sac.discount = -0.1,
            "sac.discount",
            "must be in [0, 1], got -0.1",
        ),
        (
            |c| c.sac.discount = f64::NAN,
            "sac.discount",
            "must be in [0, 1], got NaN",
        ),
        (
            |c| c.sac.batch_size = 0,
            "sac.batch_size",
            "must be >= 2, got 0",
        ),
        (|c| c.sac.batch_size = 255, "sac.batch_size", "must be even"),
        (
            |c| c.sac.initial_temperature = 0.0,
            "sac.initial_temperature",
            "must be > 0, got 0",
        ),
        (|c| c.sac.actor_lr = -1.0, "sac.actor_lr", "must be > 0"),
        (
            |c| c.sac.critic_lr = f64::INFINITY,
            "sac.critic_lr",
            "must be > 0, got inf",
        ),
        (|c| c.sac.temp_lr = 0.0, "sac.temp_lr", "must be > 0"),
        (
            |c| c.sac.adam_beta2 = 1.0,
            "sac.adam_beta2",
            "must be in [0, 1), got 1",
        ),
        (|c| c.sac.adam_eps = 0.0, "sac.adam_eps", "must be > 0"),
        (
            |c| c.sac.target_entropy = Some(f64::NEG_INFINITY),
            "sac.target_entropy",
            "a finite number",
        ),
        (
            |c| c.sac.steps_per_env = 0,
            "sac.steps_per_env",
            "must be >= 1, got 0",
        ),
        (
            |c| c.sac.actor_update_freq = 0,
            "sac.actor_update_freq",
            "must be >= 1",
        ),
        (|c| c.sac.eval_freq = 0, "sac.eval_freq", "must be >= 1"),
        (
            |c| c.sac.replay_buffer_capacity = 4,
            "sac.replay_buffer_capacity",
            "must be >= env.num_envs (8)",
        ),
        (
            |c| c.network.actor_features = vec![],
            "network.actor_features",
            "non-empty list",
        ),
        (
            |c| c.network.critic_features = vec![256, 0],
            "network.critic_features",
            "widths >= 1",
        ),
        (
            |c| c.network.log_std_max = -6.0,
            "network.log_std_max",
            "must be > network.log_std_min (-5)",
        ),
        (
            |c| c.network.layer_norm_eps = 0.0,
            "network.layer_norm_eps",
            "must be > 0",
        ),
        (|c| c.train.steps = 0, "train.steps", "must be >= 1"),
        (|c| c.train.num_demos = 0, "train.num_demos", "must be >= 1"),
        (
            |c| c.train.dataset_path = Some(String::new()),
            "train.dataset_path",
            "must not be empty",
        ),
        (
            |c| c.train.data_action_scale = Some(0.0),
            "train.data_action_scale",
            "must be > 0",
        ),
        (
            |c| c.reverse.geometric_probs = vec![0.5, 0.6],
            "reverse.geometric_probs",
            "must sum to 1",
        ),
        (
            |c| c.reverse.geometric_probs = vec![1.5, -0.5],
            "reverse.geometric_probs",
            "must be in [0, 1], got 1.5",
        ),
        (
            |c| c.reverse.geometric_probs = vec![],
            "reverse.geometric_probs",
            "must not be empty",
        ),
        (
            |c| c.reverse.per_demo_buffer_size = 0,
            "reverse.per_demo_buffer_size",
            "must be >= 1, got 0",
        ),
        (
            |c| c.reverse.reverse_step_size = 0,
            "reverse.reverse_step_size",
            "must be >= 1",
        ),
        (
            |c| c.reverse.solved_demo_weight = 0.0,
            "reverse.solved_demo_weight",
            "must be in (0, 1]",
        ),
        (
            |c| c.reverse.solved_frac_threshold = 1.1,
            "reverse.solved_frac_threshold",
            "must be in [0, 1]",
        ),
        (
            |c| c.reverse.global_success_threshold = -0.1,
            "reverse.global_success_threshold",
            "in [0, 1]",
        ),
        (
            |c| c.reverse.max_trailing_success_states = 0,
            "reverse.max_trailing_success_states",
            ">= 1",
        ),
        (
            |c| c.reverse.demo_horizon_to_max_steps_ratio = f64::NAN,
            "reverse.demo_horizon_to_max_steps_ratio",
            "a finite number",
        ),
        (
            |c| c.forward.staleness_coef = 1.5,
            "forward.staleness_coef",
            "must be in [0, 1], got 1.5",
        ),
        (
            |c| c.forward.score_temperature = 0.0,
            "forward.score_temperature",
            "must be > 0",
        ),
        (
            |c| c.forward.staleness_temperature = -0.1,
            "forward.staleness_temperature",
            "must be > 0",
        ),
        (
            |c| c.forward.num_seeds = 0,
            "forward.num_seeds",
            "must be >= 1",
        ),
        (
            |c| c.forward.score_threshold = 2.0,
            "forward.score_threshold",
            "must be in [0, 1]",
        ),
        (
            |c| c.forward.returns_buffer_size = 0,
            "forward.returns_buffer_size",
            "must be >= 1",
        ),
        (
            |c| c.forward.score_window = 21,
            "forward.score_window",
            "must be <= forward.returns_buffer_size (20)",
        ),
        (
            |c| c.env.max_episode_steps = 0,
            "env.max_episode_steps",
            "must be >= 1",
        ),
        (
            |c| c.env.env_id = String::new(),
            "env.env_id",
            "must not be empty",
        ),
        (|c| c.env.obs_dim = Some(0), "env.obs_dim", "must be >= 1"),
        (
            |c| c.env.control_mode = Some(String::new()),
            "env.control_mode",
            "must not be empty",
        ),
        (
            |c| c.eval_env.max_episode_steps = Some(0),
            "eval_env.max_episode_steps",
            "must be >= 1",
        ),
        (
            |c| c.service.num_actors = 0,
            "service.num_actors",
            "must be >= 1",
        ),
        (
            |c| c.service.lease_timeout_s = 0.0,
            "service.lease_timeout_s",
            "must be > 0",
        ),
        (
            |c| c.service.transition_batch = 0,
            "service.transition_batch",
            "must be >= 1",
        ),
        (
            |c| c.service.snapshot_every_reports = 0,
            "service.snapshot_every_reports",
            "must be >= 1",
        ),
        (
            |c| c.service.stop_at_eval_success = Some(1.5),
            "service.stop_at_eval_success",
            "must be in (0, 1]",
        ),
        (
            |c| c.name = "a/b".into(),
            "name",
            "must be a plain directory name",
        ),
        (
            |c| c.name = String::new(),
            "name",
            "must be a plain directory name",
        ),
    ];
    for (edit, key, message) in cases {
        let error = rejected(*edit);
        assert_eq!(error.key(), Some(*key), "{error}");
        let text = error.to_string();
        assert!(text.starts_with(&format!("{key}: ")), "{text}");
        assert!(
            text.contains(message),
            "{text}\n  should contain: {message}"
        );
    }
}

#[test]
fn rules_between_options_are_enforced() {
    let cases: &[(Edit, &str, &str)] = &[
        (
            |c| {
                c.sac.actor_update_freq = 20; // the sample-efficient F
                c.sac.grad_updates_per_step = 70;
            },
            "sac.grad_updates_per_step",
            "must be a multiple of sac.actor_update_freq (20) (docs/ALGORITHM.md 5.2), got 70",
        ),
        (
            |c| {
                c.sac.target_pool = 2;
                c.sac.num_min_qs = 3;
            },
            "sac.num_min_qs",
            "must be <= sac.target_pool (2)",
        ),
        (
            |c| c.sac.target_pool = 11,
            "sac.target_pool",
            "must be <= sac.critic_ensemble (10)",
        ),
        (|c| c.sac.num_min_qs = 0, "sac.num_min_qs", "must be >= 1"),
        (
            |c| {
                c.train.data_action_scale = Some(1.25);
                c.train.train_on_demo_actions = false;
            },
            "train.data_action_scale",
            "cannot be combined with train.train_on_demo_actions: false (docs/ALGORITHM.md 6.3)",
        ),
        (
            |c| {
                c.train.stage_1_only = true;
                c.train.stage_2_only = true;
            },
            "train.stage_2_only",
            "cannot be combined with train.stage_1_only",
        ),
        (
            |c| {
                c.train.mode = rfcl_core::config::TrainMode::Rlpd;
                c.train.stage_1_only = true;
            },
            "train.stage_1_only",
            "cannot be combined with train.mode: rlpd",
        ),
        (
            |c| c.train.use_orig_env_for_eval = false,
            "train.use_orig_env_for_eval",
            "is not supported by rfcl",
        ),
        (
            |c| c.train.eval_start_of_demos = true,
            "train.eval_start_of_demos",
            "is not supported by rfcl",
        ),
        (
            |c| c.train.load_as_online_buffer = true,
            "train.load_as_online_buffer",
            "docs/ALGORITHM.md 4.2",
        ),
        (
            |c| c.service.num_actors = 9,
            "env.num_envs",
            "must be >= service.num_actors (9)",
        ),
        (
            |c| c.service.num_eval_actors = 3,
            "eval_env.num_envs",
            "must be >= service.num_eval_actors (3)",
        ),
        (
            |c| c.eval_env.seed_offset = 999,
            "eval_env.seed_offset",
            "must be >= forward.num_seeds (1000)",
        ),
        (
            |c| {
                c.service.curriculum_port = 5000;
                c.service.dashboard_port = 5000;
            },
            "service.dashboard_port",
            "must differ from service.curriculum_port",
        ),
    ];
    for (edit, key, message) in cases {
        let error = rejected(*edit);
        assert_eq!(error.key(), Some(*key), "{error}");
        assert!(
            error.to_string().contains(message),
            "{error}\n  should contain: {message}"
        );
    }
}

#[test]
fn the_edges_of_each_range_are_valid() {
    let edges: &[Edit] = &[
        |c| c.sac.tau = 1.0,
        |c| c.sac.discount = 0.0,
        |c| c.sac.discount = 1.0,
        |c| c.sac.batch_size = 2,
        |c| {
            c.sac.grad_updates_per_step = 80;
            c.sac.actor_update_freq = 20;
        },
        |c| {
            c.sac.target_pool = 2; // the fast ManiSkill quirk: pool {0, 1}, min over both
            c.sac.num_min_qs = 2;
        },
        |c| c.sac.target_entropy = Some(-4.0),
        |c| c.reverse.geometric_probs = vec![1.0],
        |c| c.reverse.geometric_probs = vec![0.1; 10],
        |c| c.reverse.demo_horizon_to_max_steps_ratio = 0.0, // disables the dynamic limit
        |c| c.reverse.solved_frac_threshold = 1.0,
        |c| c.forward.staleness_coef = 0.0,
        |c| c.forward.staleness_coef = 1.0,
        |c| c.forward.score_window = 20,
        |c| c.train.data_action_scale = Some(1.25),
        |c| {
            c.train.load_as_online_buffer = true;
            c.train.load_as_offline_buffer = false;
        },
        |c| c.train.train_on_demo_actions = false,
        |c| c.service.num_eval_actors = 0,
        |c| c.service.num_actors = 8,
        |c| c.service.stop_at_eval_success = Some(1.0),
        |c| {
            c.service.curriculum_port = 5000;
            c.service.learner_port = 5001;
        },
        |c| c.eval_env.seed_offset = 1000,
    ];
    for (i, edit) in edges.iter().enumerate() {
        assert!(accepted(*edit), "edge case {i} should be valid");
    }
}

/// `env.imports` belongs to the suites whose envs come from Python modules, and names modules.
#[test]
fn env_imports_are_for_the_gymnasium_and_maniskill3_suites() {
    use rfcl_core::config::Suite;
    let err = rejected(|c| c.env.imports = vec!["my_envs".into()]);
    let text = err.to_string();
    assert!(
        text.contains("env.imports") && text.contains("only the gymnasium and maniskill3 suites"),
        "{text}"
    );
    let err = rejected(|c| {
        c.env.suite = Suite::Gymnasium;
        c.env.imports = vec!["my envs".into()];
    });
    assert!(
        err.to_string()
            .contains("'my envs' is not a Python module name"),
        "{err}"
    );
    for suite in [Suite::Gymnasium, Suite::Maniskill3] {
        let mut config = RunConfig::default();
        config.env.suite = suite;
        config.env.imports = vec!["my_package.envs".into()];
        assert!(config.validate().is_ok(), "{suite:?}");
    }
}

/// `env.success` names a callable for the gymnasium suite only.
#[test]
fn env_success_is_a_callable_of_the_gymnasium_suite() {
    use rfcl_core::config::Suite;
    let err = rejected(|c| c.env.success = Some("my_envs:reached".into()));
    assert!(
        err.to_string()
            .contains("only the gymnasium suite takes a success callable"),
        "{err}"
    );
    let err = rejected(|c| {
        c.env.suite = Suite::Gymnasium;
        c.env.success = Some("reached".into());
    });
    assert!(
        err.to_string()
            .contains("expected module:callable, got 'reached'"),
        "{err}"
    );
    assert!(accepted(|c| {
        c.env.suite = Suite::Gymnasium;
        c.env.success = Some("my_envs:reached".into());
    }));
}
