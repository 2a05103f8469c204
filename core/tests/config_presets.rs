//! The presets in `configs/`: every file resolves and validates, and each carries the values of
//! spec 8.1-8.3 for its suite, task and hyperparameter set.
use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};

use rfcl_core::config::{
    resolve_file, to_yaml, CurriculumMethod, RunConfig, StartStepSampler, Suite,
};

fn configs_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs")
}

/// Every `.yml` under `configs/`, relative to it, sorted.
fn preset_files() -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        for entry in fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                walk(&path, out);
            } else if path
                .extension()
                .is_some_and(|ext| ext == "yml" || ext == "yaml")
            {
                out.push(path);
            }
        }
    }
    let root = configs_dir();
    let mut out = Vec::new();
    walk(&root, &mut out);
    let mut files: Vec<PathBuf> = out
        .iter()
        .map(|p| p.strip_prefix(&root).unwrap().to_owned())
        .collect();
    files.sort();
    files
}

fn load(relative: &str) -> RunConfig {
    let path = configs_dir().join(relative);
    resolve_file(&path, &[]).unwrap_or_else(|e| panic!("{e}"))
}

/// The task presets (outside `configs/base/`, `configs/ablations/` and `configs/baselines/`) as
/// (file, config).
/// `*_test.yml` files are not presets of spec 8 but small configs for the project's own whole-run
/// tests (`configs/pointmaze_test.yml`), and the ablation rows change a small config on purpose;
/// they still resolve, validate and round-trip like every file.
fn task_presets() -> Vec<(String, RunConfig)> {
    preset_files()
        .into_iter()
        .filter(|file| {
            !file.starts_with("base")
                && !file.starts_with("ablations")
                && !file.starts_with("baselines")
                && !file.to_string_lossy().ends_with("_test.yml")
        })
        .map(|file| {
            let name = file.to_str().unwrap().to_owned();
            let config = load(&name);
            (name, config)
        })
        .collect()
}

#[test]
fn every_file_resolves_validates_and_round_trips() {
    let files = preset_files();
    assert!(
        files.len() >= 7 + 2 * (4 + 3 + 15 + 1),
        "found only {files:?}"
    );
    let dir = tempfile::tempdir().unwrap();
    for file in &files {
        let path = configs_dir().join(file);
        let config = resolve_file(&path, &[]).unwrap_or_else(|e| panic!("{e}"));
        let copy = dir.path().join("copy.yml");
        fs::write(&copy, to_yaml(&config)).unwrap();
        assert_eq!(
            resolve_file(&copy, &[]).unwrap(),
            config,
            "{}",
            file.display()
        );
    }
}

#[test]
fn every_file_starts_with_a_comment_saying_what_it_is() {
    for file in preset_files() {
        let text = fs::read_to_string(configs_dir().join(&file)).unwrap();
        assert!(
            text.starts_with("# "),
            "{} has no header comment",
            file.display()
        );
    }
}

#[test]
fn every_task_comes_in_both_sets_with_a_unique_run_name() {
    let presets = task_presets();
    let files: BTreeSet<&str> = presets.iter().map(|(file, _)| file.as_str()).collect();
    for file in &files {
        let twin = match file.strip_suffix("_sample_efficient.yml") {
            Some(stem) => format!("{stem}.yml"),
            None => file.replace(".yml", "_sample_efficient.yml"),
        };
        assert!(files.contains(twin.as_str()), "{file} has no {twin}");
    }
    let names: BTreeSet<&str> = presets.iter().map(|(_, c)| c.name.as_str()).collect();
    assert_eq!(names.len(), presets.len(), "run names repeat");
}

#[test]
fn the_sets_carry_spec_8_2() {
    for (file, c) in task_presets() {
        let sample_efficient = file.ends_with("_sample_efficient.yml");
        let maniskill = c.env.suite == Suite::Maniskill3;
        let plug_charger = file.contains("plug_charger");
        let sac = &c.sac;
        if sample_efficient {
            assert_eq!(
                (
                    sac.steps_per_env,
                    sac.grad_updates_per_step,
                    sac.actor_update_freq
                ),
                (1, 80, 20),
                "{file}"
            );
            assert_eq!(sac.target_pool, 10, "{file}");
            assert_eq!(
                sac.eval_freq,
                if plug_charger { 100_000 } else { 5_000 },
                "{file}"
            );
            assert_eq!(
                sac.save_freq,
                if plug_charger { 1_000_000 } else { 10_000 },
                "{file}"
            );
            assert_eq!(
                c.train.steps,
                if maniskill { 2_000_000 } else { 1_000_000 },
                "{file}"
            );
        } else {
            assert_eq!(
                (
                    sac.steps_per_env,
                    sac.grad_updates_per_step,
                    sac.actor_update_freq
                ),
                (4, 16, 1),
                "{file}"
            );
            // The fast ManiSkill quirk (spec 5.1, deviation 2): target from members {0, 1}.
            assert_eq!(sac.target_pool, if maniskill { 2 } else { 10 }, "{file}");
            assert_eq!(
                sac.eval_freq,
                if plug_charger { 100_000 } else { 50_000 },
                "{file}"
            );
            assert_eq!(
                sac.save_freq,
                if plug_charger { 1_000_000 } else { 50_000 },
                "{file}"
            );
            assert_eq!(
                c.train.steps,
                if maniskill { 4_000_000 } else { 2_000_000 },
                "{file}"
            );
        }
        // Spec 8.1, shared by all.
        assert_eq!(
            (sac.critic_ensemble, sac.num_min_qs, sac.tau),
            (10, 2, 0.005),
            "{file}"
        );
        assert_eq!(c.env.num_envs, 8, "{file}");
        assert_eq!(c.network.actor_features, [256, 256, 256], "{file}");
        assert_eq!(c.sac.num_seed_steps, 5000, "{file}");
    }
}

#[test]
fn maniskill3_presets_carry_spec_8_3() {
    // (file stem, env id, gamma, delta, phi, batch, buffer, data_action_scale)
    let rows = [
        (
            "pick_cube",
            "PickCube-v1",
            0.9,
            4,
            3.0,
            256,
            1_000_000,
            None,
        ),
        (
            "stack_cube",
            "StackCube-v1",
            0.9,
            4,
            3.0,
            256,
            1_000_000,
            None,
        ),
        (
            "peg_insertion_side",
            "PegInsertionSide-v1",
            0.99,
            4,
            3.0,
            256,
            1_000_000,
            None,
        ),
        (
            "plug_charger",
            "PlugCharger-v1",
            0.95,
            2,
            1.25,
            512,
            2_000_000,
            Some(1.25),
        ),
    ];
    for (stem, env_id, gamma, delta, phi, batch, buffer, scale) in rows {
        for file in [
            format!("maniskill3/{stem}.yml"),
            format!("maniskill3/{stem}_sample_efficient.yml"),
        ] {
            let c = load(&file);
            assert_eq!(c.env.env_id, env_id, "{file}");
            assert_eq!(c.env.suite, Suite::Maniskill3, "{file}");
            // ManiSkill3's own horizons for the two tasks its suite default (50) is too short for.
            let (horizon, eval_steps) = match stem {
                "peg_insertion_side" => (100, 500),
                "plug_charger" => (200, 1000),
                _ => (50, 500),
            };
            assert_eq!(c.env.max_episode_steps, horizon, "{file}");
            assert_eq!(
                c.env.control_mode.as_deref(),
                Some("pd_joint_delta_pos"),
                "{file}"
            );
            assert_eq!(c.sac.discount, gamma, "{file}");
            assert_eq!(c.reverse.reverse_step_size, delta, "{file}");
            assert_eq!(c.reverse.demo_horizon_to_max_steps_ratio, phi, "{file}");
            assert_eq!(c.sac.batch_size, batch, "{file}");
            assert_eq!(c.sac.replay_buffer_capacity, buffer, "{file}");
            assert_eq!(c.train.data_action_scale, scale, "{file}");
            assert_eq!(c.sac.eval_steps, eval_steps, "{file}");
            assert_eq!(c.reverse.per_demo_buffer_size, 3, "{file}");
            assert_eq!(c.forward.num_seeds, 1000, "{file}");
        }
    }
}

#[test]
fn adroit_presets_carry_spec_8_3() {
    for (stem, env_id, horizon) in [
        ("door", "AdroitHandDoorSparse-v1", 200),
        ("pen", "AdroitHandPenSparse-v1", 100),
        ("relocate", "AdroitHandRelocateSparse-v1", 200),
    ] {
        for file in [
            format!("adroit/{stem}.yml"),
            format!("adroit/{stem}_sample_efficient.yml"),
        ] {
            let c = load(&file);
            assert_eq!(
                (c.env.env_id.as_str(), c.env.suite),
                (env_id, Suite::Adroit),
                "{file}"
            );
            assert_eq!(c.env.max_episode_steps, horizon, "{file}");
            assert_eq!(c.env.control_mode, None, "{file}");
            assert_eq!(c.sac.discount, 0.99, "{file}");
            assert_eq!(c.reverse.reverse_step_size, 8, "{file}");
            assert_eq!(c.reverse.demo_horizon_to_max_steps_ratio, 3.0, "{file}");
            assert_eq!(c.sac.eval_steps, 1000, "{file}");
        }
    }
}

#[test]
fn metaworld_presets_are_the_15_hardest_tasks_with_spec_8_3() {
    let tasks = [
        "assembly",
        "bin-picking",
        "box-close",
        "disassemble",
        "hammer",
        "hand-insert",
        "pick-out-of-hole",
        "pick-place",
        "pick-place-wall",
        "push",
        "push-back",
        "shelf-place",
        "soccer",
        "stick-pull",
        "stick-push",
    ];
    let presets: Vec<_> = task_presets()
        .into_iter()
        .filter(|(file, _)| file.starts_with("metaworld/"))
        .collect();
    assert_eq!(presets.len(), 2 * tasks.len());
    for task in tasks {
        let stem = task.replace('-', "_");
        for file in [
            format!("metaworld/{stem}.yml"),
            format!("metaworld/{stem}_sample_efficient.yml"),
        ] {
            let c = load(&file);
            assert_eq!(c.env.env_id, format!("{task}-v3"), "{file}");
            assert_eq!(c.env.suite, Suite::Metaworld, "{file}");
            assert_eq!(c.env.max_episode_steps, 200, "{file}");
            assert_eq!(c.sac.discount, 0.99, "{file}");
            assert_eq!(c.reverse.reverse_step_size, 8, "{file}");
            // The reference configs' phi (the paper's table says 3).
            assert_eq!(c.reverse.demo_horizon_to_max_steps_ratio, 1.0, "{file}");
            assert_eq!(c.sac.eval_steps, 1000, "{file}");
        }
    }
}

#[test]
fn pointmaze_presets_carry_spec_7_5_and_8_3() {
    for file in ["pointmaze.yml", "pointmaze_sample_efficient.yml"] {
        let c = load(file);
        assert_eq!(
            (c.env.env_id.as_str(), c.env.suite),
            ("PointMaze-v0", Suite::Pointmaze)
        );
        assert_eq!(c.env.max_episode_steps, 300);
        assert_eq!((c.env.obs_dim, c.env.action_dim), (Some(7), Some(2)));
        assert_eq!(c.eval_env.num_envs, 4);
        assert_eq!(c.sac.discount, 0.99);
        assert_eq!(c.sac.batch_size, 512);
        assert_eq!(c.reverse.reverse_step_size, 8);
        assert_eq!(c.reverse.demo_horizon_to_max_steps_ratio, 1.0);
        assert_eq!(c.reverse.per_demo_buffer_size, 2);
        assert_eq!(c.forward.num_seeds, 34);
        assert_eq!(c.sac.eval_steps, 1000);
    }
}

/// The stage-1 ablation rows (`configs/ablations/`): per environment, one base run to the end of
/// stage 1 (PointMaze: `pointmaze_test.yml`; PickCube-v1: the fast preset with a [128, 128]
/// agent and 2 critics), and each row changes exactly its variant's keys and nothing else, so the
/// table compares the variants and only them.
#[test]
fn stage_1_ablation_rows_change_only_their_variant() {
    let to_stage_1_end = |c: &mut RunConfig| {
        c.train.stage_1_only = true;
        c.train.steps = 1_000_000;
        c.service.stop_at_eval_success = None;
    };
    let mut pointmaze = load("pointmaze_test.yml");
    to_stage_1_end(&mut pointmaze);
    let mut pick_cube = load("maniskill3/pick_cube.yml");
    to_stage_1_end(&mut pick_cube);
    pick_cube.network.actor_features = vec![128, 128];
    pick_cube.network.critic_features = vec![128, 128];
    pick_cube.sac.critic_ensemble = 2;
    pick_cube.sac.target_pool = 2;
    let variants: [(&str, &dyn Fn(&mut RunConfig)); 4] = [
        ("per_demo", &|_| {}),
        ("per_demo_no_time_limit", &|c| {
            c.reverse.demo_horizon_to_max_steps_ratio = 0.0
        }),
        ("global", &|c| {
            c.reverse.curriculum_method = CurriculumMethod::Global
        }),
        ("uniform", &|c| {
            c.reverse.start_step_sampler = StartStepSampler::Uniform
        }),
    ];
    let mut listed = BTreeSet::new();
    for (env, base, name_prefix) in [
        ("pointmaze", &pointmaze, "ablation_stage1"),
        ("pick_cube", &pick_cube, "ablation_pick_cube_stage1"),
    ] {
        for (variant, change) in &variants {
            let file = format!("ablations/{env}_stage1_{variant}.yml");
            let mut expected = base.clone();
            expected.name = format!("{name_prefix}_{variant}");
            change(&mut expected);
            assert_eq!(load(&file), expected, "{file}");
            listed.insert(file);
        }
    }
    let files: BTreeSet<String> = preset_files()
        .into_iter()
        .filter(|f| f.starts_with("ablations"))
        .map(|f| f.to_string_lossy().into_owned())
        .collect();
    assert_eq!(files, listed, "every ablation row is checked here");
}

/// The RLPD baseline (`configs/baselines/`) is `pointmaze_test.yml` with only the mode changed, so
/// a side-by-side run compares the methods and nothing else.
#[test]
fn the_rlpd_baseline_changes_only_the_mode() {
    let mut expected = load("pointmaze_test.yml");
    expected.name = "pointmaze_test_rlpd".into();
    expected.train.mode = rfcl_core::config::TrainMode::Rlpd;
    assert_eq!(load("baselines/pointmaze_test_rlpd.yml"), expected);
    assert_eq!(
        expected.train.stage_plan().unwrap(),
        rfcl_core::config::StagePlan::ForwardOnly
    );
    let forward = expected.forward_curriculum();
    assert!(!forward.include_demo_starts && forward.staleness_coef == 0.0);
}
