//! Shared by the simulator suites' whole-run tests (`tests/train_{maniskill,metaworld,adroit}.rs`):
//! the Python worker binary and one smoke run of `rfcl train` with every process taking part.
use std::path::{Path, PathBuf};
use std::time::Duration;

use rfcl_actor::env::Env;
use rfcl_actor::python::{PythonEnv, WorkerSpec};
use rfcl_core::demo::DemoSet;

use super::*;

/// Replays each demo of `set` state by state through the Rust bridge to `spec`'s worker: reset
/// with the demo's seed, set state t (the first `compared` observation values must read back
/// within 1e-5), apply action t; the success flags must be the demo's, ending in success. Load
/// `set` before calling: the worker is forked here.
pub fn replay_demos(spec: WorkerSpec, set: &DemoSet, compared: usize) {
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
            let (obs, recorded) = (&obs[..compared], &demo.obs_row(t)[..compared]);
            assert!(
                obs.iter().zip(recorded).all(|(a, b)| (a - b).abs() <= 1e-5),
                "traj_{} obs {t}: {obs:?} vs {recorded:?}",
                demo.episode_id
            );
            replayed.push(env.step(demo.action_row(t)).unwrap().success);
        }
        assert_eq!(replayed, demo.success, "traj_{}", demo.episode_id);
        assert!(demo.succeeded && demo.success.last() == Some(&true));
    }
}

/// The Python worker, next to `rfcl` (rfcl-testkit builds it when missing).
pub fn sim_worker() -> PathBuf {
    rfcl_testkit::binaries::sim_worker()
}

/// Children of `parent` named `rfcl-sim-worker` (comm is cut to 15 bytes).
pub fn sim_workers_of(parent: u64) -> Vec<u64> {
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
        let ppid = stat[close + 1..]
            .split_whitespace()
            .nth(1)
            .and_then(|p| p.parse::<u64>().ok());
        if stat[open + 1..close].starts_with("rfcl-sim-worke") && ppid == Some(parent) {
            found.push(pid);
        }
    }
    found
}

/// A short `rfcl train CONFIG` on 2 demos (tiny networks, 3,000 env steps, 2 actors and 1 eval
/// actor with one env each) in which the curriculum server, the learner, both actors (each with
/// a Python worker) and the eval actor take part, the learner receives transitions and updates,
/// the run ends on its budget with an eval and no respawn, and no process outlives it.
/// `eval_steps` makes one eval a few episodes of the task's horizon.
pub fn smoke_run(config: &str, demos: &Path, dir: &Path, env_id: &str, eval_steps: u32) {
    require_services();
    sim_worker();
    let run_dir = dir.join("run");
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join(config);
    let mut training = Training::start(
        &[
            config.display().to_string(),
            format!("train.dataset_path={}", demos.display()),
            "train.num_demos=2".into(),
            // Tiny agent and a short budget: a smoke run, not a training run.
            "network.actor_features=[32,32]".into(),
            "network.critic_features=[32,32]".into(),
            "sac.critic_ensemble=2".into(),
            "sac.target_pool=2".into(),
            "sac.batch_size=64".into(),
            "sac.num_seed_steps=500".into(),
            "sac.eval_freq=1000".into(),
            format!("sac.eval_steps={eval_steps}"),
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
        &dir.join("rfcl.stderr"),
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
    assert_eq!(summary["env_id"], env_id);
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
