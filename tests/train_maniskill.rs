//! ManiSkill3 end to end, with the real simulator and real processes:
//!
//! * `rfcl demos generate --env PickCube-v1` (ManiSkill's motion planner, then its replay into
//!   pd_joint_delta_pos with state observations) writes demos that `rfcl demos inspect` reads, and
//!   each demo, replayed from its recorded states through the Python bridge (reset with the demo's
//!   seed, set state t, apply action t), reproduces its success flags; `rfcl demos convert` turns a
//!   motion-planning file a user brings into the same form;
//! * a short `rfcl train configs/maniskill3/pick_cube.yml` (tiny networks, a few thousand env
//!   steps) in which the curriculum server, the learner, both actors (each with a Python worker)
//!   and the eval actor take part and the learner receives the transitions; no worker outlives it.
mod train_support;

use std::path::Path;
use std::process::Command;

use rfcl_actor::python::WorkerSpec;
use rfcl_core::demo::DemoSet;
use train_support::*;

fn rfcl() -> &'static str {
    env!("CARGO_BIN_EXE_rfcl")
}

fn inspect(file: &Path) -> String {
    succeed(Command::new(rfcl()).args(["demos", "inspect"]).arg(file))
}

#[test]
fn generated_demos_load_and_replay_their_success_flags() {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let file = generate_env_demos("PickCube-v1", 2, &dir.path().join("pick_cube.h5"));
    let report = inspect(&file);
    rfcl_testkit::assert_contains_all(
        &report,
        &[
            "env: PickCube-v1  control_mode: pd_joint_delta_pos",
            "episodes: 2 (2 successful)",
            "dims: obs 42, action 8, env_state 70",
            "articulations/panda     (articulation, dof 9)",
        ],
    );

    // Load the whole set before any worker is forked (no HDF5 handle may leak into a child).
    let set = DemoSet::load(&file).unwrap();
    let spec = WorkerSpec {
        suite: "maniskill3".into(),
        env_id: "PickCube-v1".into(),
        options: serde_json::json!({"max_episode_steps": 50, "control_mode": "pd_joint_delta_pos"}),
        program: sim::sim_worker(),
    };
    // The robot's qpos and qvel (the first 18 values) are read back exactly.
    sim::replay_demos(spec, &set, 18);

    // `--seed 1`: the planner's first episode (seed 0) is planned and dropped; what is left is the
    // same episode the seed-0 file holds for that seed.
    let from_1 = DemoSet::load(&generate_env_demos_from(
        "PickCube-v1",
        1,
        1,
        &dir.path().join("from_1.h5"),
    ))
    .unwrap();
    assert_eq!(from_1.demos.len(), 1);
    let seed = from_1.demos[0]
        .reset
        .seed
        .expect("a planned demo has its seed");
    assert!(seed >= 1, "seed {seed}");
    let same = set.demos.iter().find(|d| d.reset.seed == Some(seed));
    assert!(
        same.is_some_and(|d| d.env_states == from_1.demos[0].env_states),
        "the demo of seed {seed} differs from the seed-0 file's"
    );

    // `rfcl demos convert` on what a user brings: a motion-planning file under pd_joint_pos,
    // without observations.
    let record = dir.path().join("mp");
    succeed(
        Command::new(rfcl_core::python::python_program())
            .args([
                "-m",
                "mani_skill.examples.motionplanning.panda.run",
                "-e",
                "PickCube-v1",
                "-n",
                "1",
                "--only-count-success",
                "-b",
                "physx_cpu",
                "--traj-name",
                "user",
                "--record-dir",
            ])
            .arg(&record)
            .current_dir(dir.path()),
    );
    let raw = record.join("PickCube-v1/motionplanning/user.h5");
    let converted = dir.path().join("converted.h5");
    succeed(
        Command::new(rfcl())
            .args(["demos", "convert"])
            .arg(&raw)
            .arg("--out")
            .arg(&converted),
    );
    let report = inspect(&converted);
    rfcl_testkit::assert_contains_all(
        &report,
        &[
            "control_mode: pd_joint_delta_pos",
            "episodes: 1 (1 successful)",
            "dims: obs 42, action 8, env_state 70",
        ],
    );
    // Nothing was written beside the user's file.
    let beside: Vec<_> = std::fs::read_dir(raw.parent().unwrap())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert_eq!(beside.len(), 2, "{beside:?}");
}

#[test]
fn pick_cube_smoke_run_uses_every_process() {
    let dir = tempfile::tempdir().unwrap();
    let demos = generate_env_demos("PickCube-v1", 2, &dir.path().join("pick_cube.h5"));
    sim::smoke_run(
        "configs/maniskill3/pick_cube.yml",
        &demos,
        dir.path(),
        "PickCube-v1",
        50,
    );
}
