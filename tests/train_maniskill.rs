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

use rfcl_actor::env::Env;
use rfcl_actor::python::{PythonEnv, WorkerSpec};
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
    assert!(
        report.contains("env: PickCube-v1  control_mode: pd_joint_delta_pos")
            && report.contains("episodes: 2 (2 successful)")
            && report.contains("dims: obs 42, action 8, env_state 70")
            && report.contains("articulations/panda     (articulation, dof 9)"),
        "{report}"
    );

    // Load the whole set before any worker is forked (no HDF5 handle may leak into a child).
    let set = DemoSet::load(&file).unwrap();
    let spec = WorkerSpec {
        suite: "maniskill3".into(),
        env_id: "PickCube-v1".into(),
        options: serde_json::json!({"max_episode_steps": 50, "control_mode": "pd_joint_delta_pos"}),
        program: sim::sim_worker(),
    };
    let mut env = PythonEnv::start(spec, 0).unwrap();
    assert_eq!(
        env.state_layout(),
        &set.state_layout,
        "adapter and demo file agree"
    );
    for demo in &set.demos {
        let mut replayed = Vec::with_capacity(demo.len());
        for t in 0..demo.len() {
            let obs = env
                .reset_to_state(demo.reset.seed, &demo.reset.options, demo.state_row(t))
                .unwrap();
            // The robot's qpos and qvel (the first 18 values) are read back exactly.
            let recorded = &demo.obs_row(t)[..18];
            assert!(
                obs[..18]
                    .iter()
                    .zip(recorded)
                    .all(|(a, b)| (a - b).abs() <= 1e-5),
                "traj_{} obs {t}",
                demo.episode_id
            );
            replayed.push(env.step(demo.action_row(t)).unwrap().success);
        }
        assert_eq!(replayed, demo.success, "traj_{}", demo.episode_id);
        assert!(demo.succeeded && demo.success.last() == Some(&true));
    }

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
    let python = std::env::var("RFCL_PYTHON")
        .ok()
        .or_else(|| option_env!("PYO3_PYTHON").map(str::to_owned))
        .unwrap_or_else(|| "python3".into());
    let record = dir.path().join("mp");
    let planned = Command::new(&python)
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
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        planned.status.success(),
        "{}",
        String::from_utf8_lossy(&planned.stderr)
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
    assert!(
        report.contains("control_mode: pd_joint_delta_pos")
            && report.contains("episodes: 1 (1 successful)")
            && report.contains("dims: obs 42, action 8, env_state 70"),
        "{report}"
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
