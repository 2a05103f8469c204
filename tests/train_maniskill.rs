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

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use rfcl_actor::env::Env;
use rfcl_actor::python::{PythonEnv, WorkerSpec};
use rfcl_core::demo::DemoSet;
use train_support::*;

fn rfcl() -> &'static str {
    env!("CARGO_BIN_EXE_rfcl")
}

/// The Python worker is built next to `rfcl` (by `cargo build --release --workspace`).
fn worker() -> PathBuf {
    let path = Path::new(rfcl()).with_file_name("rfcl-sim-worker");
    assert!(
        path.is_file(),
        "{} is not built: run `cargo build --release --workspace`",
        path.display()
    );
    path
}

/// `rfcl demos generate --env PickCube-v1 -n N --out DIR/pick_cube.h5`.
fn generate_pick_cube(dir: &Path, n: u32) -> PathBuf {
    let out = dir.join("pick_cube.h5");
    let result = Command::new(rfcl())
        .args([
            "demos",
            "generate",
            "--env",
            "PickCube-v1",
            "-n",
            &n.to_string(),
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        result.status.success(),
        "rfcl demos generate failed: {}",
        String::from_utf8_lossy(&result.stderr)
    );
    out
}

fn inspect(file: &Path) -> String {
    let out = Command::new(rfcl())
        .args(["demos", "inspect"])
        .arg(file)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn generated_demos_load_and_replay_their_success_flags() {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let file = generate_pick_cube(dir.path(), 2);
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
        program: worker(),
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
    let out = Command::new(rfcl())
        .args(["demos", "convert"])
        .arg(&raw)
        .arg("--out")
        .arg(&converted)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
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

/// Children of `parent` named `rfcl-sim-worker` (comm is cut to 15 bytes).
fn sim_workers_of(parent: u64) -> Vec<u64> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<u64>() else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        let (Some(open), Some(close)) = (stat.find('('), stat.rfind(')')) else {
            continue;
        };
        let comm = &stat[open + 1..close];
        let ppid = stat[close + 1..]
            .split_whitespace()
            .nth(1)
            .and_then(|p| p.parse::<u64>().ok());
        if comm.starts_with("rfcl-sim-worke") && ppid == Some(parent) {
            found.push(pid);
        }
    }
    found
}

#[test]
fn pick_cube_smoke_run_uses_every_process() {
    require_services();
    worker();
    let dir = tempfile::tempdir().unwrap();
    let demos = generate_pick_cube(dir.path(), 2);
    let run_dir = dir.path().join("run");
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/maniskill3/pick_cube.yml");
    let mut training = Training::start(
        &[
            config.display().to_string(),
            format!("train.dataset_path={}", demos.display()),
            "train.num_demos=2".into(),
            // Tiny agent and a short budget: a smoke run, not a training run.
            "network.actor_features=[32,32]".into(),
            "network.critic_features=[32,32]".into(),
            "sac.critic_ensemble=2".into(),
            "sac.batch_size=64".into(),
            "sac.num_seed_steps=500".into(),
            "sac.eval_freq=1000".into(),
            "sac.eval_steps=50".into(),
            "train.steps=3000".into(),
            "env.num_envs=2".into(),
            "eval_env.num_envs=1".into(),
            "service.num_actors=2".into(),
            "service.num_eval_actors=1".into(),
            "--learner-threads".into(),
            "1".into(),
            "--run-dir".into(),
            run_dir.display().to_string(),
        ],
        &run_dir,
        &dir.path().join("rfcl.stderr"),
    );
    let processes = training.processes(Duration::from_secs(120));
    assert_eq!(
        child_pids(&processes).len(),
        2 + 2 + 1,
        "server, learner, 2 actors, 1 eval actor"
    );
    // Each actor runs its env in a Python worker; the learner and the curriculum server count the
    // transitions and episodes both train actors send.
    let actors: Vec<u64> = ["actor-0", "actor-1", "eval-actor-2"]
        .iter()
        .map(|name| child_pid(&processes, name))
        .collect();
    let mut workers = Vec::new();
    let flowing = wait_for(Duration::from_secs(240), || {
        for &actor in &actors {
            for w in sim_workers_of(actor) {
                if !workers.contains(&w) {
                    workers.push(w);
                }
            }
        }
        let health = learner_health(&processes)?;
        let state = curriculum_state(&processes)?;
        let seen = state["actors"]
            .as_array()?
            .iter()
            .filter(|a| a["actor_id"].as_u64() < Some(2) && a["env_steps"].as_u64() > Some(0))
            .count();
        (health.env_steps >= 500 && health.updates > 0 && seen == 2 && workers.len() == 3)
            .then_some(())
    });
    assert!(
        flowing.is_some(),
        "no progress (workers seen: {workers:?}):\n{}",
        training.stderr()
    );

    let status = training.wait(Duration::from_secs(600));
    let stderr = training.stderr();
    assert!(status.success(), "{status}:\n{stderr}");
    assert!(
        stderr.contains("run finished (step budget used)"),
        "{stderr}"
    );
    let summary = training.summary();
    assert_eq!(summary["env_id"], "PickCube-v1");
    assert!(
        summary["env_steps"].as_u64().unwrap() >= 2000,
        "{summary:#}"
    );
    assert!(summary["updates"].as_u64().unwrap() > 0, "{summary:#}");
    assert!(
        summary["curriculum_episodes"].as_u64().unwrap() > 0,
        "{summary:#}"
    );
    assert!(
        !summary["evals"].as_array().unwrap().is_empty(),
        "the eval actor evaluated"
    );
    assert_eq!(summary["actor_respawns"], 0, "{summary:#}");
    for pid in child_pids(&processes).into_iter().chain(workers) {
        assert!(!alive(pid), "process {pid} outlived the run");
    }
}
