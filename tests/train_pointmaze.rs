//! `rfcl train configs/pointmaze_test.yml` end to end, with real binaries on loopback: PointMaze
//! from 5 generated demos reaches an eval-success bar on the true initial-state distribution (all
//! 34 start cells); the summary, the run directory and the processes' own counters (learner Health,
//! curriculum GetState) show that transitions flowed over shared memory and leases over gRPC; no
//! child outlives the run;
//! `rfcl eval` runs the exported policy. A run whose budget is an eval point ends with its final
//! policy evaluated as that point.
//!
//! The bar is the config's own 0.9: on the 2-core development machine the run
//! gets there after 75,000-95,000 env steps, in 4-5 minutes (benches/RESULTS.md); a policy that
//! acts uniformly never does.
mod train_support;

use std::time::Duration;

use rfcl_core::video::VideoMeta;

use train_support::*;

#[test]
fn pointmaze_test_config_trains_to_its_bar() {
    let dir = tempfile::tempdir().unwrap();
    let mut training = start_test_run(dir.path(), &[stop_at_bar()], "rfcl.stderr");
    let run_dir = training.run_dir.clone();

    // While it runs: every child is up, and the learner and the curriculum server count the
    // transitions and episodes the actors send.
    let processes = training.processes(Duration::from_secs(120));
    let pids = child_pids(&processes);
    assert_eq!(
        pids.len(),
        2 + 2 + 1,
        "server, learner, 2 actors, 1 eval actor"
    );
    assert!(processes["dashboard"]
        .as_str()
        .unwrap()
        .starts_with("http://127.0.0.1:"));
    let flowing = wait_for(Duration::from_secs(120), || {
        let health = learner_health(&processes)?;
        let state = curriculum_state(&processes)?;
        let actors = state["actors"].as_array()?;
        let train_actors_seen = actors
            .iter()
            .filter(|a| a["actor_id"].as_u64() < Some(2) && a["env_steps"].as_u64() > Some(0))
            .count();
        (health.env_steps >= 2000
            && health.updates > 0
            && state["episodes"].as_u64()? > 0
            && train_actors_seen == 2)
            .then_some((health, state))
    });
    let (health, state) = flowing.unwrap_or_else(|| panic!("no progress:\n{}", training.stderr()));
    assert!(health.ok && health.policy_version > 1, "{health:?}");
    // One host: the actors' transitions come over shared memory (the learner's own counters),
    // while their leases and reports go over gRPC (the curriculum server's episodes above).
    assert!(
        health.shm_records > 0 && health.grpc_records == 0,
        "{health:?}"
    );
    assert_eq!(state["stage"], 1, "a fresh run starts in stage 1");
    // Both actors are served: the learner's shared-memory ingest takes frames from every
    // publisher in turn (one publisher once took nearly all the learner's capacity).
    let shares = wait_for(Duration::from_secs(300), || {
        let state = curriculum_state(&processes)?;
        let steps: Vec<u64> = state["actors"]
            .as_array()?
            .iter()
            .filter(|a| a["actor_id"].as_u64() < Some(2))
            .filter_map(|a| a["env_steps"].as_u64())
            .collect();
        (steps.len() == 2 && steps.iter().sum::<u64>() >= 20_000).then_some(steps)
    })
    .unwrap_or_else(|| {
        panic!(
            "the actors did not reach 20,000 env steps:\n{}",
            training.stderr()
        )
    });
    let total: u64 = shares.iter().sum();
    assert!(
        shares.iter().all(|&s| s * 4 >= total),
        "each of the 2 actors takes at least a quarter of the env steps: {shares:?}"
    );

    // The dashboard's learner panel: the curriculum server polls the learner's Health over gRPC,
    // at the address the learner announced, and shows its last progress window.
    let panel = wait_for(Duration::from_secs(60), || {
        let learner = curriculum_state(&processes)?.get("learner")?.clone();
        let window = learner.get("window")?;
        (learner["seconds_since_answer"].as_f64()? < 10.0
            && window["updates_per_s"].as_f64()? > 0.0
            && window["critic_loss"].as_f64().is_some()
            && window["time_shares"]["updating"].as_f64()? > 0.0)
            .then_some(learner)
    })
    .unwrap_or_else(|| {
        panic!(
            "no learner panel: {:?}\n{}",
            curriculum_state(&processes).map(|s| s["learner"].clone()),
            training.stderr()
        )
    });
    assert_eq!(panel["address"], processes["learner"], "{panel}");
    assert_eq!(panel["error"], serde_json::Value::Null, "{panel}");
    // The eval actor records its first evaluation's first episode (eval_env.video_every), sends
    // it to the curriculum server over gRPC, which keeps it in the run directory and serves it
    // from the dashboard.
    let video = wait_for(Duration::from_secs(120), || {
        let state = curriculum_state(&processes)?;
        serde_json::from_value::<VideoMeta>(state["videos"].as_array()?.first()?.clone()).ok()
    })
    .unwrap_or_else(|| panic!("no eval video:\n{}", training.stderr()));
    let video_name = video.file_name();
    let served = std::process::Command::new("curl")
        .args([
            "-sf",
            &format!(
                "{}videos/{video_name}",
                processes["dashboard"].as_str().unwrap()
            ),
        ])
        .output()
        .unwrap();
    assert!(served.status.success(), "GET /videos/{video_name}");
    assert_eq!(
        served.stdout,
        std::fs::read(run_dir.join("videos").join(&video_name)).unwrap()
    );
    // A whole 300-step episode: the reset state and every third step.
    let mut decoder = gif::DecodeOptions::new()
        .read_info(&served.stdout[..])
        .unwrap();
    let mut frames = 0;
    while decoder.read_next_frame().unwrap().is_some() {
        frames += 1;
    }
    assert_eq!(frames, 101, "{video_name}");
    // And a real browser renders it.
    let dom = rfcl_testkit::browser::dump_dom(
        &dir.path().join("chromium-profile"),
        processes["dashboard"].as_str().unwrap(),
    );
    for expected in [
        "<h2>Learner</h2>",
        "updates/s <b>",
        "where the learner's time goes",
        "eval episode(s) recorded",
        "href=\"/videos/v",
    ] {
        assert!(dom.contains(expected), "{expected}:\n{dom}");
    }

    let status = training.wait(Duration::from_secs(900));
    let stderr = training.stderr();
    assert!(status.success(), "{status}:\n{stderr}");
    assert!(
        stderr.contains("run finished (eval success reached)"),
        "{stderr}"
    );
    let stdout = training.stdout_lines().join("\n");
    assert!(stdout.contains("dashboard: http://127.0.0.1:"), "{stdout}");
    let summary = training.summary();
    assert_reached(&summary, BAR);
    assert_eq!(summary["sessions"], 1);
    assert_eq!(summary["actor_respawns"], 0, "no actor died");
    assert_eq!(
        summary["learner_counters"], "final",
        "the learner wrote its final counts when it stopped"
    );
    let shm = summary["transitions_shm"].as_u64().unwrap();
    assert!(
        shm >= summary["env_steps"].as_u64().unwrap(),
        "every stored transition came over shared memory: {summary:#}"
    );
    assert_eq!(summary["transitions_grpc"], 0, "{summary:#}");
    // No lease is lost, except those of episodes the actors dropped when stage 2 began (their
    // reports would have been refused): at most one per train env.
    let stage_changes = summary["stage"].as_u64().unwrap() - 1;
    assert!(summary["expired_leases"].as_u64().unwrap() <= 8 * stage_changes);

    // The run directory, and no child left behind.
    for file in [
        "config.yml",
        "summary.json",
        "train_progress.json",
        "curriculum.snapshot.json",
        "policy.safetensors",
        "logs/learner.log",
        "logs/actor-0.log",
        "logs/eval-actor-2.log",
    ] {
        assert!(run_dir.join(file).is_file(), "{file} missing");
    }
    assert!(!run_dir.join("processes.json").exists());
    let actor_log = std::fs::read_to_string(run_dir.join("logs/actor-0.log")).unwrap();
    assert!(
        actor_log.contains("transport: shared memory"),
        "{actor_log}"
    );
    for pid in pids {
        assert!(!alive(pid), "child {pid} outlived the run");
    }

    // The exported policy on held-out seeds, in-process: deterministic, one episode per cell. It
    // solves some of them (uniform actions solve none: docs/POINTMAZE.md).
    let (success, line) = eval_run(&run_dir, 34);
    assert!(line.contains("34 episodes from held-out seeds"), "{line}");
    assert!(success >= 0.1, "{line}");
}

/// `train.steps` of 10,000, a multiple of the config's 5,000-step eval points but not of its
/// 32-step iterations: the learner trains its final policy on all 10,000 steps, and `rfcl train`
/// waits for that policy's evaluation before it ends the run. Evaluations of 340 episodes
/// (4 eval envs × 25,500 steps / horizon 300) outlast the learner's exit.
#[test]
fn a_budget_on_an_eval_point_ends_with_the_final_policy_evaluated() {
    const BUDGET: u64 = 10_000;
    const EPISODES: u64 = 340;
    let dir = tempfile::tempdir().unwrap();
    let mut training = start_test_run(
        dir.path(),
        &[
            format!("train.steps={BUDGET}"),
            "sac.eval_steps=25500".into(),
        ],
        "rfcl.stderr",
    );
    let status = training.wait(Duration::from_secs(600));
    assert!(status.success(), "{status}:\n{}", training.stderr());
    let summary = training.summary();
    assert_eq!(summary["ending"], "budget", "{summary:#}");
    let evals = summary["evals"].as_array().unwrap();
    let steps: Vec<u64> = evals
        .iter()
        .map(|e| e["env_steps"].as_u64().unwrap())
        .collect();
    assert_eq!(
        steps.last(),
        Some(&BUDGET),
        "the last evaluation is the final policy's: {steps:?}\n{}",
        training.stderr()
    );
    assert_eq!(
        evals.last().unwrap()["episodes"],
        EPISODES,
        "a complete evaluation"
    );
    assert!(
        training
            .stderr()
            .contains("waiting for the evaluation of the final policy"),
        "{}",
        training.stderr()
    );
}
