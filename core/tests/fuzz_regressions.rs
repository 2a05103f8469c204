//! Replays the `demo_hdf5` and `config_overrides` fuzz corpora and every crash reproducer
//! (`fuzz/corpus/<target>/`, `fuzz/artifacts/<target>/`) through the fuzz targets' own bodies,
//! `fuzz/harness/<target>.rs`, on stable Rust without libFuzzer (docs/FUZZING.md).
use std::path::{Path, PathBuf};

#[path = "../../fuzz/harness/config_overrides.rs"]
mod config_overrides;
#[path = "../../fuzz/harness/demo_hdf5.rs"]
mod demo_hdf5;

#[path = "../../fuzz/harness/replay.rs"]
mod replay;

use replay::replay;

fn inputs(kind: &str, target: &str) -> Vec<PathBuf> {
    replay::inputs(env!("CARGO_MANIFEST_DIR"), kind, target)
}

fn non_empty(target: &str, files: &[PathBuf]) {
    replay::non_empty(target, files, 3);
}

/// A demo error names the file it is about.
fn names_the_demo_file(r: &str) -> bool {
    !r.contains('\n') && r.contains("demo.h5: ") && r.len() > "demo.h5: ".len() + 8
}

/// A config error names the layer (the file or the override) or the dotted key it is about.
fn names_the_layer_or_key(r: &str) -> bool {
    let dotted_key = r.split_once(": ").is_some_and(|(key, _)| {
        !key.is_empty()
            && key
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_' || c == '.')
    });
    !r.contains('\n')
        && (r.contains("run.yml")
            || r.starts_with("command-line override '")
            || r.starts_with("base_config cycle: ")
            || dotted_key)
}

#[test]
fn demo_hdf5_corpus_replays_without_panics() {
    let corpus = inputs("corpus", "demo_hdf5");
    non_empty("demo_hdf5", &corpus);
    replay(&corpus, demo_hdf5::run, names_the_demo_file);
}

#[test]
fn demo_hdf5_crash_reproducers_stay_fixed() {
    replay(
        &inputs("artifacts", "demo_hdf5"),
        demo_hdf5::run,
        names_the_demo_file,
    );
}

/// Crashes inside the HDF5 C library itself (`fuzz/artifacts/demo_hdf5/upstream/`): they
/// cannot be fixed in rfcl and would kill this test process (SIGSEGV), so they are not replayed
/// here; each must be listed, with its stack, in docs/FUZZING.md ("Findings").
#[test]
fn demo_hdf5_upstream_crashes_are_documented() {
    let docs =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/FUZZING.md"))
            .unwrap();
    for file in inputs("artifacts", "demo_hdf5/upstream") {
        let name = file.file_name().unwrap().to_str().unwrap();
        assert!(
            docs.contains(name),
            "{name} is in fuzz/artifacts/demo_hdf5/upstream/ but not in docs/FUZZING.md"
        );
    }
}

#[test]
fn config_overrides_corpus_replays_without_panics() {
    let corpus = inputs("corpus", "config_overrides");
    non_empty("config_overrides", &corpus);
    let rejections = replay(&corpus, config_overrides::run, names_the_layer_or_key);
    assert!(rejections > 0, "the corpus exercises no rejection at all");
}

#[test]
fn config_overrides_crash_reproducers_stay_fixed() {
    replay(
        &inputs("artifacts", "config_overrides"),
        config_overrides::run,
        names_the_layer_or_key,
    );
}

#[test]
fn config_inputs_split_at_the_separator_line() {
    let (yaml, overrides) =
        config_overrides::split("sac:\n  tau: 0.1\n%%\nseed=3\nsac.batch_size=8\n");
    assert_eq!(yaml, "sac:\n  tau: 0.1\n");
    assert_eq!(overrides, ["seed=3", "sac.batch_size=8"]);
    assert_eq!(config_overrides::split("seed: 1\n"), ("seed: 1\n", vec![]));
    assert_eq!(config_overrides::SEPARATOR, "%%");
}

/// Rewrites the seed inputs of both corpora (`cargo test -p rfcl-core --test fuzz_regressions
/// -- --ignored write_seed_corpus`); `cargo fuzz cmin` then keeps what adds coverage.
#[test]
#[ignore = "writes fuzz/corpus/{demo_hdf5,config_overrides}/seed-*: run by hand"]
fn write_seed_corpus() {
    use rfcl_core::demo::{Demo, DemoSet, ResetArgs, StateKind, StateLayout, SuccessSource};

    let corpus = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/corpus");
    let config_dir = corpus.join("config_overrides");
    std::fs::create_dir_all(&config_dir).unwrap();
    let configs = [
        ("seed-empty", ""),
        ("seed-sections", "seed: 3\nsac:\n  batch_size: 64\n  tau: 0.01\nnetwork:\n  actor_features: [32, 32]\n"),
        (
            "seed-pointmaze",
            "env:\n  env_id: PointMaze-v0\n  suite: pointmaze\n  max_episode_steps: 300\n  obs_dim: 7\n  action_dim: 2\neval_env:\n  num_envs: 4\nsac:\n  discount: 0.99\n  batch_size: 512\n  num_qs: 10\nreverse:\n  reverse_step_size: 8\n  per_demo_buffer_size: 2\nforward:\n  num_seeds: 34\n  score_transform: rankmin\ntrain:\n  dataset_path: demos/pointmaze.h5\n  data_action_scale: null\n%%\nsac.batch_size=128\nnetwork.actor_features=[64,64]\ntrain.dataset_path=null\n",
        ),
        ("seed-overrides-only", "%%\nseed=7\nsac.utd_mode=async\nenv.env_kwargs={reward_mode: sparse}\n"),
        ("seed-typo", "sac:\n  batch_sise: 64\n"),
        ("seed-wrong-type", "%%\nsac.batch_size=abc\n"),
        ("seed-base-cycle", "base_config: run.yml\n"),
    ];
    for (name, text) in configs {
        std::fs::write(config_dir.join(name), text).unwrap();
    }

    let demo_dir = corpus.join("demo_hdf5");
    std::fs::create_dir_all(&demo_dir).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let demo = |episode_id: u64, t: usize, state_dim: usize| Demo {
        episode_id,
        obs_dim: 2,
        action_dim: 1,
        state_dim,
        obs: (0..(t + 1) * 2).map(|i| i as f32 * 0.5).collect(),
        actions: (0..t).map(|i| i as f32 * -0.25).collect(),
        success: (0..t).map(|s| s + 1 == t).collect(),
        env_states: (0..(t + 1) * state_dim).map(|i| i as f32).collect(),
        succeeded: true,
        success_source: SuccessSource::Steps,
        reset: ResetArgs::default(),
    };
    let layouts = [
        ("seed-flat.h5", StateLayout::flat(3)),
        (
            "seed-ms3.h5",
            StateLayout::from_parts([
                ("actors/cube".to_owned(), StateKind::Actor, 13),
                ("articulations/arm".to_owned(), StateKind::Articulation, 15),
            ]),
        ),
        (
            "seed-fields.h5",
            StateLayout::from_parts([
                ("qpos".to_owned(), StateKind::Field, 2),
                ("qvel".to_owned(), StateKind::Field, 1),
            ]),
        ),
    ];
    for (name, layout) in layouts {
        let path = tmp.path().join(name);
        let s = layout.dim();
        let set = DemoSet {
            path: path.clone(),
            sidecar: None,
            env_id: None,
            env_info: serde_json::Value::Null,
            control_mode: None,
            obs_dim: 2,
            action_dim: 1,
            state_dim: s,
            state_layout: layout,
            demos: vec![demo(0, 2, s), demo(1, 1, s)],
        };
        set.write(&path).unwrap();
        std::fs::copy(&path, demo_dir.join(name)).unwrap();
    }
}
