//! What a user sees when a config is wrong: one line naming the file or override, the dotted key
//! and what to do.
use std::fs;
use std::path::{Path, PathBuf};

use rfcl_core::config::{resolve_file, ConfigError, Source};

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    fs::create_dir_all(path.parent().unwrap()).unwrap();
    fs::write(&path, text).unwrap();
    path
}

/// Resolves `text` written to `x.yml` with `overrides`, expecting an error; checks it is one line.
fn error_of(text: &str, overrides: &[&str]) -> (ConfigError, String, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = write(dir.path(), "x.yml", text);
    let overrides: Vec<String> = overrides.iter().map(|s| s.to_string()).collect();
    let error = resolve_file(&path, &overrides).expect_err("the config should be rejected");
    let message = error.to_string();
    assert!(!message.contains('\n'), "not one line: {message}");
    (error, message, path)
}

#[test]
fn an_unknown_key_in_a_file_names_the_file_the_key_and_a_suggestion() {
    let (error, message, path) = error_of("sac:\n  batch_sise: 512\n", &[]);
    assert_eq!(
        message,
        format!(
            "{}: unknown key 'sac.batch_sise' (did you mean 'sac.batch_size'?)",
            path.display()
        )
    );
    assert_eq!(error.key(), Some("sac.batch_sise"));
}

#[test]
fn an_unknown_key_in_an_override_names_the_override() {
    let (_, message, _) = error_of("", &["sac.batch_sise=512"]);
    assert_eq!(
        message,
        "command-line override 'sac.batch_sise=512': unknown key 'sac.batch_sise' \
         (did you mean 'sac.batch_size'?)"
    );
}

#[test]
fn suggestions_find_keys_in_other_sections_and_the_reference_names() {
    let (_, message, _) = error_of("batch_size: 512\n", &[]);
    assert!(
        message.ends_with("unknown key 'batch_size' (did you mean 'sac.batch_size'?)"),
        "{message}"
    );
    let (_, message, _) = error_of("train:\n  eval_use_orig_env: false\n", &[]);
    assert!(
        message.ends_with("(did you mean 'train.use_orig_env_for_eval'?)"),
        "{message}"
    );
    let (_, message, _) = error_of("", &["num_eval_envs=4"]);
    assert!(
        message.ends_with("(did you mean 'eval_env.num_envs'?)"),
        "{message}"
    );
    let (_, message, _) = error_of("wandb:\n  project: x\n", &[]);
    assert!(message.ends_with("unknown key 'wandb'"), "{message}");
}

#[test]
fn an_unknown_key_in_a_base_names_the_base() {
    let dir = tempfile::tempdir().unwrap();
    let base = write(dir.path(), "base/b.yml", "reverse:\n  reverse_step: 4\n");
    let path = write(dir.path(), "x.yml", "base_config: base/b.yml\n");
    let error = resolve_file(&path, &[]).unwrap_err();
    assert_eq!(
        error.to_string(),
        format!(
            "{}: unknown key 'reverse.reverse_step' (did you mean 'reverse.reverse_step_size'?)",
            base.display()
        )
    );
}

#[test]
fn free_form_env_kwargs_accept_any_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = write(
        dir.path(),
        "x.yml",
        "env:\n  env_kwargs:\n    anything: {goes: [1]}\n",
    );
    let config = resolve_file(&path, &["env.env_kwargs.more=2".into()]).unwrap();
    assert_eq!(config.env.env_kwargs.len(), 2);
}

#[test]
fn a_wrong_type_names_the_key_what_was_expected_and_what_was_found() {
    let (error, message, path) = error_of("sac:\n  batch_size: abc\n", &[]);
    assert_eq!(
        message,
        format!(
            "{}: sac.batch_size: expected an unsigned integer, got \"abc\"",
            path.display()
        )
    );
    assert!(matches!(
        error,
        ConfigError::WrongType {
            origin: Source::File(_),
            ..
        }
    ));

    let cases = [
        (
            "sac:\n  batch_size: 256.5\n",
            "sac.batch_size: expected an unsigned integer, got 256.5",
        ),
        (
            "sac:\n  batch_size: -1\n",
            "sac.batch_size: expected an unsigned integer in [0, 4294967295], got -1",
        ),
        (
            "service:\n  learner_port: 70000\n",
            "service.learner_port: expected an unsigned integer in [0, 65535], got 70000",
        ),
        (
            "sac:\n  tau: fast\n",
            "sac.tau: expected a number, got \"fast\"",
        ),
        (
            "train:\n  shuffle_demos: 1\n",
            "train.shuffle_demos: expected a boolean, got 1",
        ),
        (
            "network:\n  actor_features: [64, big]\n",
            "network.actor_features[1]: expected an unsigned integer, got \"big\"",
        ),
        (
            "network:\n  actor_features: 64\n",
            "network.actor_features: expected a list, got 64",
        ),
        ("sac: 5\n", "sac: expected a mapping, got 5"),
        (
            "sac:\n  batch_size: null\n",
            "sac.batch_size: expected an unsigned integer, got null",
        ),
        (
            "train:\n  dataset_path: 5\n",
            "train.dataset_path: expected a string, got 5",
        ),
        (
            "sac:\n  utd_mode: 3\n",
            "sac.utd_mode: expected a string, got 3",
        ),
    ];
    for (text, expected) in cases {
        let (_, message, _) = error_of(text, &[]);
        assert!(
            message.ends_with(expected),
            "{message}\n  should end with: {expected}"
        );
    }
}

#[test]
fn a_wrong_type_in_an_override_names_the_override() {
    let (_, message, _) = error_of("", &["sac.batch_size=abc"]);
    assert_eq!(
        message,
        "command-line override 'sac.batch_size=abc': sac.batch_size: expected an unsigned integer, \
         got \"abc\""
    );
}

#[test]
fn an_unknown_enum_value_lists_the_choices_and_suggests_one() {
    let (_, message, _) = error_of("forward:\n  score_transform: rank_min\n", &[]);
    assert!(
        message.ends_with(
            "forward.score_transform: unknown value \"rank_min\", expected one of: rankmin, rank, \
             constant, identity, power, softmax (did you mean 'rankmin'?)"
        ),
        "{message}"
    );
}

#[test]
fn an_out_of_range_value_names_the_file_that_set_it_and_the_range() {
    let dir = tempfile::tempdir().unwrap();
    let base = write(dir.path(), "base.yml", "sac:\n  tau: 1.5\n");
    let path = write(dir.path(), "x.yml", "base_config: base.yml\nseed: 3\n");
    let error = resolve_file(&path, &[]).unwrap_err();
    assert_eq!(
        error.to_string(),
        format!("{}: sac.tau: must be in (0, 1], got 1.5", base.display())
    );
    let error = resolve_file(&path, &["sac.tau=0".into()]).unwrap_err();
    assert_eq!(
        error.to_string(),
        "command-line override 'sac.tau=0': sac.tau: must be in (0, 1], got 0"
    );
}

#[test]
fn a_rule_broken_by_defaults_names_no_file() {
    // grad_updates_per_step keeps its default 16; the override makes it no multiple of F.
    let (_, message, _) = error_of("", &["sac.actor_update_freq=3"]);
    assert_eq!(
        message,
        "sac.grad_updates_per_step: must be a multiple of sac.actor_update_freq (3) (docs/ALGORITHM.md 5.2), got 16"
    );
}

#[test]
fn a_base_cycle_is_reported_with_the_chain() {
    let dir = tempfile::tempdir().unwrap();
    let a = write(dir.path(), "a.yml", "base_config: b.yml\n");
    let b = write(dir.path(), "b.yml", "base_config: a.yml\n");
    let error = resolve_file(&a, &[]).unwrap_err();
    assert!(matches!(error, ConfigError::Cycle { .. }));
    assert_eq!(
        error.to_string(),
        format!(
            "base_config cycle: {} -> {} -> {}",
            a.display(),
            b.display(),
            a.display()
        )
    );

    let selfish = write(dir.path(), "self.yml", "base_config: ./self.yml\n");
    let error = resolve_file(&selfish, &[]).unwrap_err();
    assert!(
        matches!(error, ConfigError::Cycle { ref chain } if chain.len() == 2),
        "{error}"
    );
}

#[test]
fn a_file_used_twice_by_different_branches_is_no_cycle() {
    let dir = tempfile::tempdir().unwrap();
    write(dir.path(), "common.yml", "seed: 1\n");
    write(dir.path(), "a.yml", "base_config: common.yml\n");
    write(dir.path(), "b.yml", "base_config: common.yml\n");
    let path = write(dir.path(), "x.yml", "base_config: [a.yml, b.yml]\n");
    assert_eq!(resolve_file(&path, &[]).unwrap().seed, 1);
}

#[test]
fn a_missing_base_names_the_including_file_and_where_it_looked() {
    let (error, message, path) = error_of("base_config: base/nope.yml\n", &[]);
    assert!(matches!(error, ConfigError::MissingBase { .. }));
    let looked = path.parent().unwrap().join("base/nope.yml");
    assert_eq!(
        message,
        format!(
            "{}: base_config 'base/nope.yml' not found (looked for {})",
            path.display(),
            looked.display()
        )
    );
}

#[test]
fn a_missing_file_is_a_read_error() {
    let error = resolve_file(Path::new("/nonexistent/config.yml"), &[]).unwrap_err();
    assert!(matches!(error, ConfigError::Read { .. }));
    assert!(
        error
            .to_string()
            .starts_with("/nonexistent/config.yml: cannot read: "),
        "{error}"
    );
    // The OS error is in the message, so it is not also the source: a chain printed with
    // `{:#}` names it once.
    assert!(std::error::Error::source(&error).is_none());
}

#[test]
fn malformed_files_and_overrides_are_explained() {
    let cases: [(&str, &[&str], &str); 6] = [
        ("sac: [1,\n", &[], "invalid YAML: "),
        (
            "- 1\n- 2\n",
            &[],
            "expected a YAML mapping of sections at the top level (env:, sac:, ...), got a list",
        ),
        (
            "base_config: {a: 1}\n",
            &[],
            "base_config must be a path or a list of paths",
        ),
        (
            "",
            &["sac.batch_size"],
            "expected KEY=VALUE, e.g. sac.batch_size=512",
        ),
        (
            "",
            &["sac..batch_size=3"],
            "the key must be dotted names, e.g. sac.batch_size",
        ),
        ("", &["sac.batch_size=[1,"], "invalid YAML: "),
    ];
    for (text, overrides, expected) in cases {
        let (_, message, _) = error_of(text, overrides);
        assert!(
            message.contains(expected),
            "{message}\n  should contain: {expected}"
        );
    }
    let (_, message, _) = error_of("sac:\n  tau: 0.1\n  tau: 0.2\n", &[]);
    assert!(
        message.contains("invalid YAML: duplicate mapping key: tau at line 3"),
        "{message}"
    );
    assert!(!message.contains("DuplicateKeyPolicy"), "{message}");
}

#[test]
fn a_base_config_that_is_not_yaml_is_named_by_kind_not_echoed() {
    let dir = tempfile::tempdir().unwrap();
    let notes = dir.path().join("notes.txt");
    // Plain prose parses as a YAML string: the error names its kind, not its content.
    std::fs::write(
        &notes,
        "my private notes, the key is hunter2 and more text\n",
    )
    .unwrap();
    let run = dir.path().join("run.yml");
    std::fs::write(&run, "base_config: notes.txt\n").unwrap();
    let err = resolve_file(&run, &[]).unwrap_err().to_string();
    assert!(
        !err.contains("hunter2"),
        "the file's content is echoed: {err}"
    );
    assert!(
        err.contains("notes.txt")
            && err.contains("expected a YAML mapping")
            && err.contains("got a string"),
        "{err}"
    );
}
