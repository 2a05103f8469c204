//! Demo datasets (spec 6.1): every reader path on files written here, selection, inspect output.

use std::path::{Path, PathBuf};

use rfcl_core::demo::{Demo, DemoError, DemoSet, ResetArgs, StateKind, StateLayout, SuccessSource};
use serde_json::json;

const OBS: usize = 5;
const ACT: usize = 3;

/// A demo with T actions whose values encode (episode, array, index); success flags are set from
/// step `success_from` on.
fn demo(
    episode_id: u64,
    t: usize,
    state_dim: usize,
    success_from: Option<usize>,
    seed: Option<u64>,
) -> Demo {
    let values = |tag: f32, n: usize| -> Vec<f32> {
        (0..n)
            .map(|i| episode_id as f32 * 1000.0 + tag * 100.0 + i as f32 * 0.25)
            .collect()
    };
    let success: Vec<bool> = (0..t)
        .map(|s| success_from.is_some_and(|f| s >= f))
        .collect();
    Demo {
        episode_id,
        obs_dim: OBS,
        action_dim: ACT,
        state_dim,
        obs: values(1.0, (t + 1) * OBS),
        actions: values(2.0, t * ACT),
        succeeded: success.last() == Some(&true),
        success,
        env_states: values(3.0, (t + 1) * state_dim),
        success_source: SuccessSource::Steps,
        reset: ResetArgs {
            seed,
            options: json!({}),
        },
    }
}

fn set(path: &Path, layout: StateLayout, demos: Vec<Demo>) -> DemoSet {
    DemoSet {
        path: path.to_path_buf(),
        sidecar: Some(DemoSet::sidecar_path(path)),
        env_id: Some("PickCube-v1".into()),
        env_info: json!({
            "env_id": "PickCube-v1",
            "env_kwargs": {"control_mode": "pd_joint_delta_pos", "obs_mode": "state"},
            "max_episode_steps": 50,
        }),
        control_mode: Some("pd_joint_delta_pos".into()),
        obs_dim: OBS,
        action_dim: ACT,
        state_dim: layout.dim(),
        state_layout: layout,
        demos,
    }
}

/// actors/cube (13) and articulations/panda (13 + 2·2 = 17): 30 values.
fn ms3_layout() -> StateLayout {
    StateLayout::from_parts([
        ("actors/cube".to_owned(), StateKind::Actor, 13),
        (
            "articulations/panda".to_owned(),
            StateKind::Articulation,
            17,
        ),
    ])
}

/// Four MS3 demos: 0 succeeds, 1 fails, 2 succeeds (with reset options), 3 succeeds.
fn ms3_set(dir: &Path) -> DemoSet {
    let layout = ms3_layout();
    let s = layout.dim();
    let mut demos = vec![
        demo(0, 6, s, Some(4), Some(10)),
        demo(1, 5, s, None, Some(11)),
        demo(2, 7, s, Some(3), Some(12)),
        demo(3, 4, s, Some(1), None),
    ];
    demos[2].reset.options =
        json!({"initial_state_dict": {"qpos": [0.5, -1.0]}, "reconfigure": true});
    for demo in &mut demos {
        unit_orientations(&layout, demo);
    }
    set(&dir.join("demos.h5"), layout, demos)
}

/// Gives every actor and articulation root of `demo` a unit orientation (a rotation about z by
/// a different angle in every state), as a simulator's states have.
fn unit_orientations(layout: &StateLayout, demo: &mut Demo) {
    let dim = demo.state_dim;
    for (t, state) in demo.env_states.chunks_exact_mut(dim).enumerate() {
        for e in layout.entries() {
            if matches!(e.kind, StateKind::Actor | StateKind::Articulation) {
                let half = 0.1 * t as f32;
                state[e.offset + 3..e.offset + 7].copy_from_slice(&[
                    half.cos(),
                    0.0,
                    0.0,
                    half.sin(),
                ]);
            }
        }
    }
}

fn write_ms3(dir: &Path) -> DemoSet {
    let set = ms3_set(dir);
    set.write(&set.path).unwrap();
    set
}

fn shape(path: &Path, dataset: &str) -> Vec<usize> {
    hdf5::File::open(path)
        .unwrap()
        .dataset(dataset)
        .unwrap()
        .shape()
}

#[test]
fn ms3_nested_file_round_trips_through_write_and_load() {
    let dir = tempfile::tempdir().unwrap();
    let set = write_ms3(dir.path());
    assert_eq!(shape(&set.path, "traj_0/env_states/actors/cube"), [7, 13]);
    assert_eq!(
        shape(&set.path, "traj_0/env_states/articulations/panda"),
        [7, 17]
    );
    assert_eq!(shape(&set.path, "traj_2/obs"), [8, OBS]);
    assert_eq!(shape(&set.path, "traj_2/actions"), [7, ACT]);

    let loaded = DemoSet::load(&set.path).unwrap();
    assert_eq!(loaded, set);
    let cube = loaded.state_layout.get("actors/cube").unwrap();
    assert_eq!(
        (cube.kind, cube.offset, cube.len),
        (StateKind::Actor, 0, 13)
    );
    let panda = loaded.state_layout.get("articulations/panda").unwrap();
    assert_eq!((panda.offset, panda.dof()), (13, Some(2)));
    let d = &loaded.demos[2];
    assert_eq!(d.len(), 7);
    assert_eq!(d.num_states(), 8);
    assert_eq!(d.obs_row(7), &set.demos[2].obs[7 * OBS..]);
    assert_eq!(d.action_row(1)[0], 2000.0 + 200.0 + 3.0 * 0.25);
    assert_eq!(
        loaded
            .state_layout
            .slice("articulations/panda", d.state_row(1))
            .unwrap(),
        &d.state_row(1)[13..]
    );
    assert_eq!(d.first_success(), Some(3));
    assert_eq!(d.success_count(), 4);
    assert_eq!(
        d.reset.options["initial_state_dict"]["qpos"],
        json!([0.5, -1.0])
    );
}

#[test]
fn flat_ms2_form_is_written_and_read_as_one_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ms2.h5");
    let layout = StateLayout::flat(9);
    let set = set(
        &path,
        layout,
        vec![
            demo(5, 3, 9, Some(2), Some(7)),
            demo(9, 4, 9, Some(0), Some(8)),
        ],
    );
    set.write(&path).unwrap();
    assert_eq!(shape(&path, "traj_9/env_states"), [5, 9]);

    let loaded = DemoSet::load(&path).unwrap();
    assert!(loaded.state_layout.is_flat());
    assert_eq!(loaded.state_layout.entries()[0].name, "env_states");
    assert_eq!(loaded, set);
}

#[test]
fn named_fields_keep_the_file_link_order() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("door.h5");
    let layout = StateLayout::from_parts([
        ("qpos".to_owned(), StateKind::Field, 4),
        ("qvel".to_owned(), StateKind::Field, 4),
        ("door_body_pos".to_owned(), StateKind::Field, 3),
    ]);
    let set = set(&path, layout, vec![demo(0, 5, 11, Some(4), Some(3))]);
    set.write(&path).unwrap();
    assert_eq!(shape(&path, "traj_0/env_states/door_body_pos"), [6, 3]);

    let loaded = DemoSet::load(&path).unwrap();
    let names: Vec<&str> = loaded
        .state_layout
        .entries()
        .iter()
        .map(|e| e.name.as_str())
        .collect();
    assert_eq!(
        names,
        ["qpos", "qvel", "door_body_pos"],
        "creation order, not name order"
    );
    assert_eq!(loaded, set);
}

/// A file as h5py writes it for Adroit/MetaWorld: no tracked creation order, float64 obs, a 1-D
/// field, success as uint8, an MS2-style sidecar with `info.success`.
#[test]
fn h5py_style_named_fields_file_reads_in_name_order_with_conversions() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("relocate.h5");
    let t = 3;
    {
        let file = hdf5::File::create(&path).unwrap();
        let g = file.create_group("traj_4").unwrap();
        let obs: Vec<f64> = (0..(t + 1) * 2).map(|i| i as f64 + 0.5).collect();
        g.new_dataset::<f64>()
            .shape([t + 1, 2])
            .create("obs")
            .unwrap()
            .write_raw(&obs[..])
            .unwrap();
        let actions = vec![0.25f32; t];
        g.new_dataset::<f32>()
            .shape([t, 1])
            .create("actions")
            .unwrap()
            .write_raw(&actions[..])
            .unwrap();
        g.new_dataset::<u8>()
            .shape([t])
            .create("success")
            .unwrap()
            .write_raw(&[0u8, 1, 1][..])
            .unwrap();
        let states = g.create_group("env_states").unwrap();
        let target: Vec<f32> = (0..(t + 1) * 3).map(|i| 100.0 + i as f32).collect();
        states
            .new_dataset::<f32>()
            .shape([t + 1, 3])
            .create("target_pos")
            .unwrap()
            .write_raw(&target[..])
            .unwrap();
        let qpos: Vec<f32> = (0..=t).map(|i| i as f32).collect();
        states
            .new_dataset::<f32>()
            .shape([t + 1])
            .create("qpos")
            .unwrap()
            .write_raw(&qpos[..])
            .unwrap();
    }
    let sidecar = json!({
        "env_info": {"env_id": "AdroitHandRelocateSparse-v1", "max_episode_steps": 200},
        "episodes": [{"episode_id": 4, "reset_kwargs": {"seed": 21}, "info": {"success": true}}],
    });
    std::fs::write(path.with_extension("json"), sidecar.to_string()).unwrap();

    let loaded = DemoSet::load(&path).unwrap();
    let names: Vec<(&str, usize)> = loaded
        .state_layout
        .entries()
        .iter()
        .map(|e| (e.name.as_str(), e.len))
        .collect();
    assert_eq!(
        names,
        [("qpos", 1), ("target_pos", 3)],
        "name order; a 1-D field is one column"
    );
    assert_eq!(
        (loaded.obs_dim, loaded.action_dim, loaded.state_dim),
        (2, 1, 4)
    );
    assert_eq!(
        loaded.env_id.as_deref(),
        Some("AdroitHandRelocateSparse-v1")
    );
    let d = &loaded.demos[0];
    assert_eq!(d.obs_row(1), [2.5, 3.5]);
    assert_eq!(d.state_row(2), [2.0, 106.0, 107.0, 108.0]);
    assert_eq!(d.success, [false, true, true]);
    assert!(d.succeeded);
    assert_eq!(
        d.reset,
        ResetArgs {
            seed: Some(21),
            options: json!({})
        }
    );
}

#[test]
fn missing_sidecar_is_allowed_and_reported() {
    let dir = tempfile::tempdir().unwrap();
    let set = write_ms3(dir.path());
    std::fs::remove_file(set.path.with_extension("json")).unwrap();

    let loaded = DemoSet::load(&set.path).unwrap();
    assert_eq!(loaded.sidecar, None);
    assert_eq!(loaded.env_id, None);
    assert!(loaded.demos.iter().all(|d| d.reset == ResetArgs::default()));
    assert_eq!(ResetArgs::default().options, json!({}));
    // Without the sidecar's flags the outcome is the last step's flag.
    let outcomes: Vec<bool> = loaded.demos.iter().map(|d| d.succeeded).collect();
    assert_eq!(outcomes, [true, false, true, true]);
    assert!(
        loaded.summary().contains("sidecar: none"),
        "{}",
        loaded.summary()
    );
}

#[test]
fn sidecar_success_flag_labels_the_final_step_when_the_file_has_no_success_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let set = write_ms3(dir.path());
    {
        let file = hdf5::File::open_rw(&set.path).unwrap();
        for id in 0..4 {
            file.group(&format!("traj_{id}"))
                .unwrap()
                .unlink("success")
                .unwrap();
        }
    }
    let loaded = DemoSet::load(&set.path).unwrap();
    let d0 = &loaded.demos[0];
    assert_eq!(d0.success_source, SuccessSource::EpisodeFlag);
    assert_eq!(d0.success, [false, false, false, false, false, true]);
    assert!(loaded.demos[1].success.iter().all(|&s| !s));
    assert!(loaded.summary().contains("labels the final step only"));
}

#[test]
fn reset_seed_comes_from_reset_kwargs_then_episode_seed() {
    let dir = tempfile::tempdir().unwrap();
    let set = write_ms3(dir.path());
    let sidecar = json!({
        "env_info": {"env_id": "PickCube-v1"},
        "episodes": [
            {"episode_id": 0, "reset_kwargs": {"seed": [42]}, "episode_seed": 1, "success": true},
            {
                "episode_id": 1, "reset_kwargs": {}, "episode_seed": 77, "success": false,
                "control_mode": "pd_joint_pos",
            },
            {"episode_id": 2, "episode_seed": 5, "success": true},
            {"episode_id": 3, "reset_kwargs": {"seed": null, "options": null}, "success": true},
        ],
    });
    std::fs::write(
        set.path.with_extension("json"),
        serde_json::to_string_pretty(&sidecar).unwrap(),
    )
    .unwrap();

    let loaded = DemoSet::load(&set.path).unwrap();
    let seeds: Vec<Option<u64>> = loaded.demos.iter().map(|d| d.reset.seed).collect();
    assert_eq!(seeds, [Some(42), Some(77), Some(5), None]);
    assert!(loaded.demos.iter().all(|d| d.reset.options == json!({})));
    assert_eq!(
        loaded.control_mode.as_deref(),
        Some("pd_joint_pos"),
        "first episode with a mode"
    );
}

#[test]
fn select_skips_failures_and_takes_the_first_in_file_order_without_shuffle() {
    let dir = tempfile::tempdir().unwrap();
    let set = ms3_set(dir.path());
    let chosen = set.select(3, false, 0).unwrap();
    let ids: Vec<u64> = chosen.demos.iter().map(|d| d.episode_id).collect();
    assert_eq!(ids, [0, 2, 3]);
    assert_eq!(chosen.state_layout, set.state_layout);
    assert_eq!(chosen.demos[1], set.demos[2]);
}

#[test]
fn shuffled_select_is_deterministic_per_seed_and_never_takes_a_failed_episode() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("many.h5");
    // 12 demos; odd ids fail.
    let demos = (0..12)
        .map(|id| demo(id, 3, 4, (id % 2 == 0).then_some(1), Some(id)))
        .collect();
    let set = set(&path, StateLayout::flat(4), demos);
    let ids = |seed| -> Vec<u64> {
        set.select(4, true, seed)
            .unwrap()
            .demos
            .iter()
            .map(|d| d.episode_id)
            .collect()
    };

    let mut orders = std::collections::HashSet::new();
    for seed in 0..20 {
        let picked = ids(seed);
        assert_eq!(
            picked,
            ids(seed),
            "seed {seed} must pick the same demos twice"
        );
        assert_eq!(picked.len(), 4);
        assert!(
            picked.iter().all(|id| id % 2 == 0),
            "seed {seed} picked a failed episode: {picked:?}"
        );
        orders.insert(picked);
    }
    assert!(
        orders.len() > 5,
        "shuffling should depend on the seed: {orders:?}"
    );
}

#[test]
fn select_fails_when_too_few_episodes_succeeded() {
    let dir = tempfile::tempdir().unwrap();
    let set = ms3_set(dir.path());
    let err = set.select(4, true, 1).unwrap_err();
    assert!(
        matches!(
            err,
            DemoError::NotEnoughDemos {
                wanted: 4,
                successful: 3,
                total: 4,
                ..
            }
        ),
        "{err}"
    );
    assert_eq!(
        err.to_string(),
        format!(
            "{}: 4 demos requested but only 3 of 4 episodes succeeded",
            set.path.display()
        )
    );
}

#[test]
fn select_rejects_a_demo_that_never_succeeds() {
    let dir = tempfile::tempdir().unwrap();
    let mut set = ms3_set(dir.path());
    // The sidecar calls episode 1 a success, but no step is flagged.
    set.demos[1].succeeded = true;
    set.write(&set.path).unwrap();
    let loaded = DemoSet::load(&set.path).unwrap();
    let err = loaded.select(2, false, 0).unwrap_err();
    assert!(
        matches!(err, DemoError::NeverSucceeds { episode_id: 1, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("traj_1"), "{err}");
    assert!(
        err.to_string().contains("success state at the end"),
        "{err}"
    );
}

#[test]
fn check_dims_compares_with_the_configured_env() {
    let dir = tempfile::tempdir().unwrap();
    let set = ms3_set(dir.path());
    set.check_dims(None, None).unwrap();
    set.check_dims(Some(OBS), Some(ACT)).unwrap();
    let err = set.check_dims(Some(7), None).unwrap_err();
    assert_eq!(
        err.to_string(),
        format!(
            "{}: obs dim 5 does not match env.obs_dim 7",
            set.path.display()
        )
    );
    let err = set.check_dims(Some(OBS), Some(8)).unwrap_err();
    assert_eq!(
        err.to_string(),
        format!(
            "{}: action dim 3 does not match env.action_dim 8",
            set.path.display()
        )
    );
}

#[test]
fn summary_lists_episodes_dims_layout_and_seeds() {
    let dir = tempfile::tempdir().unwrap();
    let set = write_ms3(dir.path());
    let text = DemoSet::load(&set.path).unwrap().summary();
    for expected in [
        "env: PickCube-v1  control_mode: pd_joint_delta_pos  max_episode_steps: 50",
        "episodes: 4 (3 successful), T min 4 / mean 5.5 / max 7",
        "dims: obs 5, action 3, env_state 30",
        "actors/cube          (actor)",
        "articulations/panda  (articulation, dof 2)",
    ] {
        assert!(text.contains(expected), "missing {expected:?} in\n{text}");
    }
    let row = |id| {
        text.lines()
            .find(|l| l.trim_start().starts_with(&format!("traj_{id} ")))
            .unwrap()
            .to_owned()
    };
    let fields = |id| {
        row(id)
            .split_whitespace()
            .take(5)
            .map(str::to_owned)
            .collect::<Vec<_>>()
    };
    assert_eq!(fields(0), ["traj_0", "6", "yes", "4", "10"]);
    assert_eq!(fields(1), ["traj_1", "5", "no", "-", "11"]);
    assert_eq!(fields(3), ["traj_3", "4", "yes", "1", "-"]);
    assert!(row(2).contains("initial_state_dict"), "{}", row(2));
}

#[test]
fn state_layout_serialises_and_rejects_gaps() {
    let layout = ms3_layout();
    let text = serde_json::to_string(&layout).unwrap();
    assert_eq!(serde_json::from_str::<StateLayout>(&text).unwrap(), layout);
    let gap = json!([
        {"name": "actors/a", "kind": "actor", "offset": 0, "len": 13},
        {"name": "qpos", "kind": "field", "offset": 14, "len": 2},
    ])
    .to_string();
    let err = serde_json::from_str::<StateLayout>(&gap).unwrap_err();
    assert!(err.to_string().contains("qpos starts at 14"), "{err}");
}

// ---------------------------------------------------------------------------------------------
// Broken files: each gives its one-line error naming the file.

fn load_err(path: &Path) -> DemoError {
    let err = DemoSet::load(path).unwrap_err();
    let text = err.to_string();
    assert!(!text.contains('\n'), "multi-line error: {text}");
    assert!(
        text.starts_with(&path.display().to_string()),
        "error does not name the file: {text}"
    );
    err
}

/// Writes the MS3 set, then lets `edit` break the file through the hdf5 crate.
fn broken(edit: impl FnOnce(&hdf5::File)) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = write_ms3(dir.path()).path;
    edit(&hdf5::File::open_rw(&path).unwrap());
    (dir, path)
}

fn replace_f32(file: &hdf5::File, name: &str, shape: &[usize]) {
    file.unlink(name).unwrap();
    let data = vec![0.5f32; shape.iter().product()];
    file.new_dataset::<f32>()
        .shape(shape)
        .create(name)
        .unwrap()
        .write_raw(&data[..])
        .unwrap();
}

#[test]
fn missing_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("nope.h5");
    let err = load_err(&path);
    assert!(matches!(err, DemoError::NotFound { .. }));
    assert_eq!(
        err.to_string(),
        format!("{}: demo file not found", path.display())
    );
}

#[test]
fn a_directory_given_as_the_demo_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("demos.h5");
    std::fs::create_dir(&path).unwrap();
    let err = load_err(&path);
    assert!(matches!(err, DemoError::IsDirectory { .. }), "{err}");
    assert_eq!(
        err.to_string(),
        format!(
            "{}: is a directory; expected an HDF5 demo file (a ManiSkill trajectory .h5)",
            path.display()
        )
    );
}

/// Replaces `name` (shape `shape`) with values that are finite except `value` at flat index `at`.
fn poison_f32(file: &hdf5::File, name: &str, shape: &[usize], at: usize, value: f32) {
    let ds = file.dataset(name).unwrap();
    let mut data = ds.read_raw::<f32>().unwrap();
    assert_eq!(data.len(), shape.iter().product::<usize>());
    data[at] = value;
    ds.write_raw(&data[..]).unwrap();
}

#[test]
fn nan_in_observations_names_episode_step_and_column() {
    // traj_2 obs is [8, OBS]: flat index 3 * OBS + 4 is step 3, column 4.
    let (_dir, path) = broken(|f| poison_f32(f, "traj_2/obs", &[8, OBS], 3 * OBS + 4, f32::NAN));
    let err = load_err(&path);
    assert!(matches!(err, DemoError::NonFinite { .. }), "{err}");
    assert_eq!(
        err.to_string(),
        format!(
            "{}: traj_2/obs has NaN at step 3, column 4: demos must hold finite numbers",
            path.display()
        )
    );
}

#[test]
fn infinity_in_env_states_and_actions_is_refused() {
    let (_dir, path) = broken(|f| {
        poison_f32(
            f,
            "traj_0/env_states/actors/cube",
            &[7, 13],
            13 + 2,
            f32::INFINITY,
        )
    });
    let err = load_err(&path).to_string();
    assert!(
        err.contains("traj_0/env_states/actors/cube has inf at step 1, column 2"),
        "{err}"
    );
    let (_dir, path) = broken(|f| poison_f32(f, "traj_3/actions", &[4, ACT], 0, f32::NEG_INFINITY));
    let err = load_err(&path).to_string();
    assert!(
        err.contains("traj_3/actions has -inf at step 0, column 0"),
        "{err}"
    );
}

/// An actor's orientation that is not a unit quaternion is damage: refused at load, naming the
/// dataset, the step, the quaternion and its norm.
#[test]
fn an_orientation_that_is_not_a_unit_quaternion_is_refused() {
    // traj_1's cube is [6, 13]: step 2's quaternion is columns 3..7; scaled to norm 2.
    let (_dir, path) = broken(|f| {
        let ds = f.dataset("traj_1/env_states/actors/cube").unwrap();
        let mut data = ds.read_raw::<f32>().unwrap();
        for q in &mut data[2 * 13 + 3..2 * 13 + 7] {
            *q *= 2.0;
        }
        ds.write_raw(&data[..]).unwrap();
    });
    let err = load_err(&path);
    assert!(
        matches!(err, DemoError::NotUnitQuaternion { step: 2, .. }),
        "{err}"
    );
    let text = err.to_string();
    assert!(
        text.starts_with(&format!(
            "{}: traj_1/env_states/actors/cube has orientation (w, x, y, z) [",
            path.display()
        )) && text.ends_with(
            "at step 2, of norm 2: an orientation must be a unit quaternion (norm within 0.001 of 1)"
        ),
        "{text}"
    );
}

#[test]
fn text_file_renamed_h5() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("demos.h5");
    std::fs::write(&path, "episode,obs\n0,1.0\n".repeat(100)).unwrap();
    let err = load_err(&path);
    assert!(matches!(err, DemoError::NotHdf5 { .. }), "{err}");
    assert!(err.to_string().contains("not an HDF5 file"));
}

#[test]
fn no_traj_groups() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("empty.h5");
    hdf5::File::create(&path)
        .unwrap()
        .create_group("data")
        .unwrap();
    assert!(matches!(load_err(&path), DemoError::NoTrajectories { .. }));
}

#[test]
fn traj_group_without_an_integer_id() {
    let (_dir, path) = broken(|f| drop(f.create_group("traj_extra").unwrap()));
    let err = load_err(&path);
    assert!(
        err.to_string()
            .contains("'traj_extra' is not named traj_<integer episode id>"),
        "{err}"
    );
}

#[test]
fn missing_actions_dataset() {
    let (_dir, path) = broken(|f| f.unlink("traj_3/actions").unwrap());
    let err = load_err(&path);
    assert_eq!(
        err.to_string(),
        format!("{}: traj_3 has no 'actions' dataset", path.display())
    );
}

#[test]
fn missing_env_states() {
    let (_dir, path) = broken(|f| f.unlink("traj_0/env_states").unwrap());
    let err = load_err(&path);
    assert_eq!(
        err.to_string(),
        format!("{}: traj_0 has no 'env_states' dataset", path.display())
    );
}

#[test]
fn obs_rows_do_not_match_actions() {
    // traj_2 has T = 7; make it T = 49 with 51 obs rows.
    let (_dir, path) = broken(|f| {
        replace_f32(f, "traj_2/actions", &[49, ACT]);
        replace_f32(f, "traj_2/obs", &[51, OBS]);
    });
    let err = load_err(&path);
    assert_eq!(
        err.to_string(),
        format!(
            "{}: traj_2: obs has 51 rows but actions has 49: expected T+1 = 50",
            path.display()
        )
    );
}

#[test]
fn success_length_does_not_match_actions() {
    let (_dir, path) = broken(|f| {
        f.unlink("traj_1/success").unwrap();
        f.new_dataset::<bool>()
            .shape([9])
            .create("traj_1/success")
            .unwrap()
            .write_raw(&[false; 9][..])
            .unwrap();
    });
    let err = load_err(&path);
    assert!(
        err.to_string()
            .ends_with("traj_1: success has 9 rows but actions has 5: expected T = 5"),
        "{err}"
    );
}

#[test]
fn env_state_rows_do_not_match_actions() {
    let (_dir, path) = broken(|f| replace_f32(f, "traj_0/env_states/actors/cube", &[5, 13]));
    let err = load_err(&path);
    assert!(
        err.to_string().ends_with(
            "traj_0: env_states/actors/cube has 5 rows but actions has 6: expected T+1 = 7"
        ),
        "{err}"
    );
}

#[test]
fn obs_dim_differs_between_episodes() {
    let (_dir, path) = broken(|f| replace_f32(f, "traj_2/obs", &[8, OBS + 1]));
    let err = load_err(&path);
    assert!(
        err.to_string()
            .ends_with("traj_2 has obs dim 6 but traj_0 has 5"),
        "{err}"
    );
}

#[test]
fn env_state_layout_differs_between_episodes() {
    let (_dir, path) = broken(|f| f.unlink("traj_3/env_states/articulations/panda").unwrap());
    let err = load_err(&path);
    assert!(
        matches!(
            err,
            DemoError::InconsistentDims {
                episode_id: 3,
                what: "env_states",
                first_episode_id: 0,
                ..
            }
        ),
        "{err}"
    );
    assert!(
        err.to_string()
            .contains("actors/cube (13), articulations/panda (17)"),
        "{err}"
    );
}

#[test]
fn actor_state_of_the_wrong_width() {
    let (_dir, path) = broken(|f| replace_f32(f, "traj_0/env_states/actors/cube", &[7, 12]));
    let err = load_err(&path);
    assert!(
        err.to_string()
            .contains("traj_0/env_states/actors/cube has 12 columns, expected 13"),
        "{err}"
    );
}

#[test]
fn obs_stored_as_a_dict_group() {
    let (_dir, path) = broken(|f| {
        f.unlink("traj_0/obs").unwrap();
        f.create_group("traj_0/obs").unwrap();
    });
    let err = load_err(&path);
    assert!(
        err.to_string()
            .contains("traj_0/obs is not a dataset (record the demos with obs_mode \"state\")"),
        "{err}"
    );
}

#[test]
fn malformed_json_sidecar_reports_line_and_column() {
    let dir = tempfile::tempdir().unwrap();
    let set = write_ms3(dir.path());
    let json = set.path.with_extension("json");
    std::fs::write(&json, "{\n  \"env_info\": {},\n  \"episodes\": [,]\n}\n").unwrap();
    let err = DemoSet::load(&set.path).unwrap_err();
    assert!(matches!(err, DemoError::Sidecar { .. }));
    let text = err.to_string();
    assert!(
        text.starts_with(&format!("{}: malformed JSON sidecar: ", json.display())),
        "{text}"
    );
    assert!(text.contains("line 3 column"), "{text}");
}

#[test]
fn sidecar_seed_of_the_wrong_type() {
    let dir = tempfile::tempdir().unwrap();
    let set = write_ms3(dir.path());
    let sidecar =
        r#"{"env_info": {}, "episodes": [{"episode_id": 0, "reset_kwargs": {"seed": "abc"}}]}"#;
    std::fs::write(set.path.with_extension("json"), sidecar).unwrap();
    let text = DemoSet::load(&set.path).unwrap_err().to_string();
    assert!(
        text.contains("expected a non-negative integer seed, got \"abc\" at line 1 column"),
        "{text}"
    );
}

#[test]
fn sidecar_without_an_entry_for_a_trajectory() {
    let dir = tempfile::tempdir().unwrap();
    let set = write_ms3(dir.path());
    let json = set.path.with_extension("json");
    let episodes = json!([{"episode_id": 0}, {"episode_id": 1}, {"episode_id": 3}]);
    let sidecar = json!({"env_info": {}, "episodes": episodes});
    std::fs::write(&json, sidecar.to_string()).unwrap();
    let text = DemoSet::load(&set.path).unwrap_err().to_string();
    assert_eq!(
        text,
        format!(
            "{}: no episodes[] entry with episode_id 2 (for traj_2)",
            json.display()
        )
    );
}

#[test]
fn write_rejects_inconsistent_demos() {
    let dir = tempfile::tempdir().unwrap();
    let mut set = ms3_set(dir.path());
    set.demos[1].obs.pop();
    let text = set.write(&set.path).unwrap_err().to_string();
    assert!(
        text.contains("traj_1: obs holds 29 values, expected (T+1)·obs_dim = 30"),
        "{text}"
    );
    let mut set = ms3_set(dir.path());
    set.demos[2].episode_id = 0;
    assert!(set
        .write(&set.path)
        .unwrap_err()
        .to_string()
        .contains("episode_id 0 appears twice"));
}
