//! Resolution: base_config chains and lists, deep merge, overrides, aliases, dataset paths, and
//! the round trip through `to_yaml`.
use std::fs;
use std::path::{Path, PathBuf};

use rfcl_core::config::{resolve_file, to_yaml, ConfigError, RunConfig, UtdMode};

/// Writes `text` to `dir/name` (creating directories) and returns the path.
fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    fs::create_dir_all(path.parent().unwrap()).unwrap();
    fs::write(&path, text).unwrap();
    path
}

fn overrides(args: &[&str]) -> Vec<String> {
    args.iter().map(|arg| arg.to_string()).collect()
}

#[test]
fn a_file_without_a_base_overrides_only_what_it_sets() {
    let dir = tempfile::tempdir().unwrap();
    let path = write(dir.path(), "x.yml", "sac:\n  batch_size: 128\n");
    let config = resolve_file(&path, &[]).unwrap();
    let mut expected = RunConfig::default();
    expected.sac.batch_size = 128;
    assert_eq!(config, expected);
}

#[test]
fn an_empty_file_is_the_default_config() {
    let dir = tempfile::tempdir().unwrap();
    let path = write(dir.path(), "empty.yml", "# nothing but a comment\n");
    assert_eq!(resolve_file(&path, &[]).unwrap(), RunConfig::default());
}

#[test]
fn bases_chain_over_several_levels_and_the_child_wins() {
    let dir = tempfile::tempdir().unwrap();
    write(
        dir.path(),
        "base/root.yml",
        "seed: 1\nsac:\n  batch_size: 64\n  tau: 0.01\n",
    );
    write(
        dir.path(),
        "base/middle.yml",
        "base_config: root.yml\nseed: 2\nsac:\n  batch_size: 32\n",
    );
    let leaf = write(
        dir.path(),
        "tasks/leaf.yml",
        "base_config: ../base/middle.yml\nseed: 3\n",
    );
    let config = resolve_file(&leaf, &[]).unwrap();
    assert_eq!(config.seed, 3); // leaf over middle over root
    assert_eq!(config.sac.batch_size, 32); // middle over root
    assert_eq!(config.sac.tau, 0.01); // root only
    assert_eq!(config.sac.discount, RunConfig::default().sac.discount); // nobody
}

#[test]
fn a_list_of_bases_merges_left_to_right_then_the_file() {
    let dir = tempfile::tempdir().unwrap();
    write(dir.path(), "a.yml", "seed: 1\nname: from_a\n");
    write(dir.path(), "b.yml", "seed: 2\n");
    let path = write(
        dir.path(),
        "c.yml",
        "base_config: [a.yml, b.yml]\nsac:\n  tau: 0.5\n",
    );
    let config = resolve_file(&path, &[]).unwrap();
    assert_eq!(config.seed, 2);
    assert_eq!(config.name, "from_a");
    assert_eq!(config.sac.tau, 0.5);
}

#[test]
fn mappings_merge_deeply_and_sequences_replace() {
    let dir = tempfile::tempdir().unwrap();
    write(
        dir.path(),
        "base.yml",
        "network:\n  actor_features: [512, 512, 512]\n  critic_features: [128]\n\
         env:\n  env_kwargs:\n    robot: panda\n    sim: {freq: 100, substeps: 2}\n",
    );
    let path = write(
        dir.path(),
        "child.yml",
        "base_config: base.yml\nnetwork:\n  actor_features: [64]\n\
         env:\n  env_kwargs:\n    sim: {freq: 50}\n",
    );
    let config = resolve_file(&path, &[]).unwrap();
    assert_eq!(config.network.actor_features, [64]); // replaced, not merged element-wise
    assert_eq!(config.network.critic_features, [128]); // sibling kept
    let kwargs = serde_json::Value::Object(config.env.env_kwargs);
    assert_eq!(
        kwargs,
        serde_json::json!({"robot": "panda", "sim": {"freq": 50, "substeps": 2}})
    );
}

#[test]
fn overrides_set_scalars_lists_strings_and_null_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let path = write(
        dir.path(),
        "x.yml",
        "train:\n  dataset_path: /data/demos.h5\n  data_action_scale: 1.25\n",
    );
    let config = resolve_file(
        &path,
        &overrides(&[
            "sac.batch_size=512",
            "network.actor_features=[64, 64]",
            "train.dataset_path=null",
            "train.data_action_scale=",
            "sac.utd_mode=async",
            "env.control_mode=pd_ee_delta_pose",
            "env.env_kwargs.robot_uids=panda",
            "seed=1",
            "seed=2",
        ]),
    )
    .unwrap();
    assert_eq!(config.sac.batch_size, 512);
    assert_eq!(config.network.actor_features, [64, 64]);
    assert_eq!(config.train.dataset_path, None);
    assert_eq!(config.train.data_action_scale, None); // an empty value is YAML null
    assert_eq!(config.sac.utd_mode, UtdMode::Async);
    assert_eq!(config.env.control_mode.as_deref(), Some("pd_ee_delta_pose"));
    assert_eq!(config.env.env_kwargs["robot_uids"], "panda");
    assert_eq!(config.seed, 2); // the last override wins
}

#[test]
fn num_qs_is_the_reference_alias_of_target_pool() {
    let dir = tempfile::tempdir().unwrap();
    write(dir.path(), "base.yml", "sac:\n  target_pool: 5\n");
    let path = write(
        dir.path(),
        "x.yml",
        "base_config: base.yml\nsac:\n  num_qs: 2\n",
    );
    assert_eq!(resolve_file(&path, &[]).unwrap().sac.target_pool, 2);
    let config = resolve_file(&path, &overrides(&["sac.num_qs=3"])).unwrap();
    assert_eq!(config.sac.target_pool, 3);

    let both = write(
        dir.path(),
        "both.yml",
        "sac:\n  num_qs: 2\n  target_pool: 2\n",
    );
    let error = resolve_file(&both, &[]).unwrap_err();
    assert!(matches!(error, ConfigError::Malformed { .. }), "{error}");
    assert!(error.to_string().contains("set only one"), "{error}");
}

#[test]
fn a_relative_dataset_path_is_relative_to_the_file_that_sets_it() {
    let dir = tempfile::tempdir().unwrap();
    write(
        dir.path(),
        "suite/base.yml",
        "train:\n  dataset_path: ../demos/./pick.h5\n",
    );
    let task = write(
        dir.path(),
        "suite/tasks/task.yml",
        "base_config: ../base.yml\n",
    );
    let config = resolve_file(&task, &[]).unwrap();
    let expected = std::path::absolute(dir.path().join("demos/pick.h5")).unwrap();
    assert_eq!(config.train.dataset_path.as_deref(), expected.to_str());

    let absolute = write(
        dir.path(),
        "abs.yml",
        "train:\n  dataset_path: /srv/demos.h5\n",
    );
    let config = resolve_file(&absolute, &[]).unwrap();
    assert_eq!(config.train.dataset_path.as_deref(), Some("/srv/demos.h5"));
}

#[cfg(unix)]
#[test]
fn relative_paths_follow_symlinked_directories_like_the_os_does() {
    let dir = tempfile::tempdir().unwrap();
    let root = fs::canonicalize(dir.path()).unwrap();
    write(&root, "real/common.yml", "seed: 5\n");
    write(
        &root,
        "real/sub/task.yml",
        "base_config: ../common.yml\ntrain:\n  dataset_path: ../demos/x.h5\n",
    );
    std::os::unix::fs::symlink(root.join("real/sub"), root.join("link")).unwrap();
    // `link/../common.yml` is `real/common.yml` for the OS, not `common.yml` next to `link`.
    let config = resolve_file(&root.join("link/task.yml"), &[]).unwrap();
    assert_eq!(config.seed, 5);
    let expected = root.join("real/demos/x.h5");
    assert_eq!(config.train.dataset_path.as_deref(), expected.to_str());
}

#[test]
fn a_relative_dataset_path_override_is_relative_to_the_working_directory() {
    let dir = tempfile::tempdir().unwrap();
    let path = write(dir.path(), "x.yml", "");
    let config = resolve_file(&path, &overrides(&["train.dataset_path=demos/x.h5"])).unwrap();
    let expected = std::env::current_dir().unwrap().join("demos/x.h5");
    assert_eq!(config.train.dataset_path.as_deref(), expected.to_str());
}

#[test]
fn to_yaml_resolves_back_to_the_same_config() {
    let mut config = RunConfig {
        name: "round_trip".into(),
        demo_seed: Some(7),
        ..RunConfig::default()
    };
    config.sac.tau = 0.1 + 0.2; // not exactly representable in decimal
    config.sac.target_entropy = Some(-3.5);
    config.sac.actor_lr = 1e-7;
    config.sac.utd_mode = UtdMode::Async;
    config.network.actor_features = vec![64, 32];
    config.train.dataset_path = Some("/data/it's \"quoted\": yes.h5".into());
    config.train.data_action_scale = Some(1.25);
    config.env.control_mode = Some("null".into()); // a string that looks like YAML null
    config
        .env
        .env_kwargs
        .insert("flag".into(), serde_json::json!("true"));
    config
        .env
        .env_kwargs
        .insert("nested".into(), serde_json::json!({"a": [1, 2.5, null]}));
    config.reverse.geometric_probs = vec![0.7, 0.3];

    let dir = tempfile::tempdir().unwrap();
    let yaml = to_yaml(&config);
    let path = write(dir.path(), "resolved.yml", &yaml);
    assert_eq!(resolve_file(&path, &[]).unwrap(), config, "{yaml}");
    let path = write(dir.path(), "default.yml", &to_yaml(&RunConfig::default()));
    assert_eq!(resolve_file(&path, &[]).unwrap(), RunConfig::default());
}

mod round_trip_property {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn numbers_and_strings_survive_to_yaml(
            seed in any::<u64>(),
            tau in 1e-12f64..=1.0,
            discount in 0.0f64..=1.0,
            entropy in -1e6f64..1e6,
            port in 1u16..,
            name in "[a-z][a-z0-9_-]{0,15}",
            kwarg in "\\PC{0,20}",
        ) {
            let mut config = RunConfig { seed, name, ..RunConfig::default() };
            config.sac.tau = tau;
            config.sac.discount = discount;
            config.sac.target_entropy = Some(entropy);
            config.service.dashboard_port = port;
            config.env.env_kwargs.insert("text".into(), kwarg.into());
            let dir = tempfile::tempdir().unwrap();
            let path = write(dir.path(), "x.yml", &to_yaml(&config));
            prop_assert_eq!(resolve_file(&path, &[]).unwrap(), config);
        }
    }
}
