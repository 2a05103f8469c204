//! The MetaWorld and Adroit demo sources through the `rfcl` CLI, with the real simulators:
//!
//! * `rfcl demos generate --env metaworld/pick-place-v3` writes scripted demos that `rfcl demos
//!   inspect` reads and that, restored state by state through the Python bridge, reproduce their
//!   observations and success flags;
//! * `rfcl demos convert --suite adroit --task door` (and the same with the task read from a
//!   D4RL file name) converts a small file written in D4RL's format (tests/adroit_d4rl.py);
//! * unknown tasks, files of another task and files that are not HDF5 give errors that name them
//!   and say what was expected.
mod train_support;

use std::path::Path;
use std::process::{Command, Output};

use rfcl_actor::python::WorkerSpec;
use rfcl_core::demo::DemoSet;
use rfcl_testkit::demos::write_d4rl_door;

fn rfcl(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rfcl"))
        .args(args)
        .output()
        .unwrap()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn ok(out: Output) -> String {
    assert!(out.status.success(), "{}", stderr(&out));
    String::from_utf8_lossy(&out.stdout).into_owned() + &stderr(&out)
}

/// rfcl's error line(s): the command failed and said `error: ...`.
fn error(out: Output) -> String {
    assert!(
        !out.status.success(),
        "expected a failure: {}",
        stderr(&out)
    );
    let text = stderr(&out);
    assert!(text.contains("error: "), "{text}");
    text
}

fn inspect(file: &Path) -> String {
    ok(rfcl(&["demos", "inspect", s(file)]))
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn metaworld_demos_are_generated_and_replay_through_the_bridge() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("demos/pick_place.h5");
    let log = ok(rfcl(&[
        "demos",
        "generate",
        "--env",
        "metaworld/pick-place-v3",
        "-n",
        "2",
        "--out",
        s(&file),
    ]));
    // The generator's per-episode progress is passed on, then rfcl's check of the file.
    assert!(log.contains("seed 0: first success flag"), "{log}");
    assert!(
        log.contains("generated 2 pick-place-v3 demos (2 successful"),
        "{log}"
    );
    let report = inspect(&file);
    rfcl_testkit::assert_contains_all(
        &report,
        &[
            "env: pick-place-v3",
            "max_episode_steps: 200",
            "episodes: 2 (2 successful)",
            "dims: obs 39, action 4, env_state 62",
        ],
    );
    let sidecar: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(file.with_extension("json")).unwrap())
            .unwrap();
    assert_eq!(sidecar["env_info"]["suite"], "metaworld");

    // Each demo, restored state by state through the Rust bridge (reset with its seed, set state
    // t, apply action t), reproduces its observations and success flags. The set is loaded before
    // the worker is forked.
    let set = DemoSet::load(&file).unwrap();
    assert_eq!(
        set.demos.iter().map(|d| d.reset.seed).collect::<Vec<_>>(),
        [Some(0), Some(1)]
    );
    let spec = WorkerSpec {
        suite: "metaworld".into(),
        env_id: "pick-place-v3".into(),
        options: serde_json::json!({"max_episode_steps": 200}),
        program: train_support::sim::sim_worker(),
    };
    let compared = set.demos[0].obs_row(0).len();
    train_support::sim::replay_demos(spec, &set, compared);
}

#[test]
fn adroit_d4rl_file_converts_and_loads() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("door-human-v1.hdf5");
    write_d4rl_door(&src, 1, 1, 10);

    let out = dir.path().join("door.h5");
    let log = ok(rfcl(&[
        "demos",
        "convert",
        "--suite",
        "adroit",
        "--task",
        "door",
        s(&src),
        "--out",
        s(&out),
    ]));
    assert!(
        log.contains("episode 0: T = 10, success at end True"),
        "{log}"
    );
    assert!(
        log.contains("converted 2 AdroitHandDoorSparse-v1 demos (1 successful"),
        "{log}"
    );
    let report = inspect(&out);
    rfcl_testkit::assert_contains_all(
        &report,
        &[
            "env: AdroitHandDoorSparse-v1",
            "episodes: 2 (1 successful)",
            "dims: obs 39, action 28, env_state 63",
        ],
    );
    // Suite and task from the file name (door-human-v1.hdf5, no .json sidecar); --episodes.
    let auto = dir.path().join("auto.h5");
    let log = ok(rfcl(&[
        "demos",
        "convert",
        s(&src),
        "--out",
        s(&auto),
        "--episodes",
        "1",
    ]));
    assert!(
        log.contains("converted 1 AdroitHandDoorSparse-v1 demos (1 successful"),
        "{log}"
    );
    assert!(inspect(&auto).contains("episodes: 1 (1 successful)"));

    // Loaded here, after the last child process (no HDF5 handle can leak into one).
    let set = DemoSet::load(&out).unwrap();
    assert_eq!(set.demos.len(), 2);
    assert!(set.demos.iter().all(|d| d.len() == 10));
    assert!(set.demos[0].succeeded && !set.demos[1].succeeded);
    // Each episode resets to its own initial state (spec 7.4).
    assert!(set.demos[0].reset.options["initial_state_dict"]["door_body_pos"].is_array());
}

#[test]
fn unknown_tasks_and_wrong_files_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let nowhere = dir.path().join("never.h5");

    // A MetaWorld task without a scripted policy: the known ones are listed.
    let err = error(rfcl(&[
        "demos",
        "generate",
        "--env",
        "metaworld/pick-plaice-v3",
        "-n",
        "1",
        "--out",
        s(&nowhere),
    ]));
    assert!(
        err.contains("--env metaworld/pick-plaice-v3")
            && err.contains("no scripted policy for task 'pick-plaice-v3'")
            && err.contains("pick-place-v3")
            && err.contains("stick-pull-v3"),
        "{err}"
    );
    // Adroit demos are converted, not generated.
    let err = error(rfcl(&[
        "demos",
        "generate",
        "--env",
        "adroit/door",
        "--out",
        s(&nowhere),
    ]));
    assert!(err.contains("rfcl demos convert --suite adroit"), "{err}");

    // An unknown Adroit task, before the file is even looked at.
    let err = error(rfcl(&[
        "demos",
        "convert",
        "--suite",
        "adroit",
        "--task",
        "hammer",
        "x.hdf5",
        "--out",
        s(&nowhere),
    ]));
    assert!(
        err.contains("--task hammer: unknown Adroit task; expected one of door, pen, relocate"),
        "{err}"
    );
    // No task given and none in the path.
    let src = dir.path().join("human.hdf5");
    write_d4rl_door(&src, 0, 1, 3);
    let err = error(rfcl(&[
        "demos",
        "convert",
        "--suite",
        "adroit",
        s(&src),
        "--out",
        s(&nowhere),
    ]));
    assert!(
        err.contains("cannot tell the Adroit task") && err.contains("give --task"),
        "{err}"
    );
    // A Door file converted as Pen: the converter names the file and the missing field.
    let err = error(rfcl(&[
        "demos",
        "convert",
        "--task",
        "pen",
        s(&src),
        "--out",
        s(&nowhere),
    ]));
    assert!(
        err.contains("AdroitHandPenSparse-v1")
            && err.contains("D4RL file lacks 'infos/desired_orien'"),
        "{err}"
    );
    // Not HDF5 at all.
    let text = dir.path().join("door.hdf5");
    std::fs::write(&text, "not hdf5").unwrap();
    let err = error(rfcl(&[
        "demos",
        "convert",
        "--task",
        "door",
        s(&text),
        "--out",
        s(&nowhere),
    ]));
    assert!(err.contains("door.hdf5: not an HDF5 file"), "{err}");
    // A suite convert does not take.
    let err = error(rfcl(&[
        "demos",
        "convert",
        "--suite",
        "metaworld",
        s(&src),
        "--out",
        s(&nowhere),
    ]));
    assert!(
        err.contains("--suite metaworld") && err.contains("maniskill3 and adroit"),
        "{err}"
    );
    assert!(!nowhere.exists());
}
