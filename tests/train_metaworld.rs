//! MetaWorld end to end, with the real simulator and real processes: 2 scripted pick-place-v3
//! demos from `rfcl demos generate --env metaworld/pick-place-v3`, then a short `rfcl train
//! configs/metaworld/pick_place.yml` (tiny networks, a few thousand env steps) in which the
//! curriculum server, the learner, both actors (each with a Python worker) and the eval actor take
//! part and the learner receives the transitions; no process outlives the run.
mod train_support;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use train_support::*;

fn rfcl() -> &'static str {
    env!("CARGO_BIN_EXE_rfcl")
}

/// The Python worker is built next to `rfcl` (by `cargo build --release --workspace`).
fn require_worker() {
    let path = Path::new(rfcl()).with_file_name("rfcl-sim-worker");
    assert!(
        path.is_file(),
        "{} is not built: run `cargo build --release --workspace`",
        path.display()
    );
}

/// `rfcl demos generate --env metaworld/pick-place-v3 -n N --out DIR/pick_place.h5`.
fn generate_pick_place(dir: &Path, n: u32) -> PathBuf {
    let out = dir.join("pick_place.h5");
    let result = Command::new(rfcl())
        .args([
            "demos",
            "generate",
            "--env",
            "metaworld/pick-place-v3",
            "-n",
            &n.to_string(),
        ])
        .arg("--out")
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

#[test]
fn pick_place_smoke_run_uses_every_process() {
    require_services();
    require_worker();
    let dir = tempfile::tempdir().unwrap();
    let demos = generate_pick_place(dir.path(), 2);
    let run_dir = dir.path().join("run");
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/metaworld/pick_place.yml");
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
            "sac.eval_steps=200".into(),
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
    assert_eq!(summary["env_id"], "pick-place-v3");
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
