//! A run stopped with SIGINT (Ctrl-C) stops every child cleanly, exits 130 and writes its summary;
//! `rfcl train --resume RUN_DIR` continues it (curriculum snapshot, learner checkpoint) to its bar,
//! counting wall time and evals over both sessions, evaluating no point twice, with the first
//! session's `--learner-threads`.
//! The bar is the config's 0.9, as in train_pointmaze.rs.
mod train_support;

use std::time::Duration;

use train_support::*;

#[test]
fn sigint_then_resume_runs_to_completion() {
    let dir = tempfile::tempdir().unwrap();
    // Not the default thread count on a 2-core machine (1), to see that `--resume` keeps it.
    let mut first = start_test_run(
        dir.path(),
        &[stop_at_bar(), "--learner-threads".into(), "2".into()],
        "first.stderr",
    );
    let run_dir = first.run_dir.clone();
    let processes = first.processes(Duration::from_secs(120));
    // Stop after the first complete evaluation.
    let progress = run_dir.join("train_progress.json");
    wait_for(Duration::from_secs(300), || {
        let p: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&progress).ok()?).ok()?;
        (!p["evals"].as_array()?.is_empty()).then_some(())
    })
    .unwrap_or_else(|| panic!("no eval:\n{}", first.stderr()));
    signal(first.pid(), rustix::process::Signal::INT);
    let status = first.wait(Duration::from_secs(180));
    assert_eq!(status.code(), Some(130), "{}", first.stderr());
    let stopped = first.summary();
    assert_eq!(stopped["ending"], "interrupted");
    // Records the learner took in but never used because it stopped count too: the two services'
    // env steps agree up to the counted causes on an interrupted run as well.
    assert_eq!(
        stopped["env_steps_accounting"]["explained"], true,
        "{stopped:#}"
    );
    assert!(
        first
            .stderr()
            .contains(&format!("rfcl train --resume {}", run_dir.display())),
        "says how to continue: {}",
        first.stderr()
    );
    for pid in child_pids(&processes) {
        assert!(!alive(pid), "child {pid} outlived the interrupted session");
    }
    assert!(
        run_dir.join("checkpoint").is_dir(),
        "the learner checkpointed"
    );
    let steps_before = stopped["env_steps"].as_u64().unwrap();
    let episodes_before = stopped["curriculum_episodes"].as_u64().unwrap();
    assert!(steps_before > 0 && episodes_before > 0);

    // Resumed without a CONFIG: the run's stored one, with the overrides given.
    let mut resumed = Training::start(
        &[
            "--resume".into(),
            run_dir.display().to_string(),
            stop_at_bar(),
        ],
        &run_dir,
        &dir.path().join("resumed.stderr"),
    );
    // The services continue from where they stopped, not from zero.
    let processes = resumed.processes(Duration::from_secs(180));
    let (health, state) = wait_for(Duration::from_secs(60), || {
        Some((learner_health(&processes)?, curriculum_state(&processes)?))
    })
    .unwrap_or_else(|| panic!("services not answering:\n{}", resumed.stderr()));
    assert!(
        health.env_steps >= steps_before,
        "{health:?} vs {steps_before}"
    );
    assert!(state["episodes"].as_u64().unwrap() >= episodes_before);

    let status = resumed.wait(Duration::from_secs(900));
    assert!(status.success(), "{status}:\n{}", resumed.stderr());
    let summary = resumed.summary();
    assert_reached(&summary, BAR);
    assert_eq!(summary["sessions"], 2);
    let learner_log = std::fs::read_to_string(run_dir.join("logs/learner.log")).unwrap();
    let sessions_on_2_threads = learner_log
        .lines()
        .filter(|l| l.contains("SAC updates on the CPU threads=2 "))
        .count();
    assert_eq!(
        sessions_on_2_threads, 2,
        "--learner-threads 2 of the first session kept by --resume:\n{learner_log}"
    );
    assert!(summary["env_steps"].as_u64().unwrap() > steps_before);
    assert!(summary["wall_s"].as_f64().unwrap() > stopped["wall_s"].as_f64().unwrap());
    // No point is evaluated twice: the resumed session's eval actor goes on after the first
    // session's complete evaluations (the config evaluates every 5,000 env steps).
    let points: Vec<u64> = summary["evals"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["env_steps"].as_u64().unwrap() / 5000)
        .collect();
    let mut distinct = points.clone();
    distinct.dedup();
    assert_eq!(points, distinct, "{:#}", summary["evals"]);
    // The first session's evals are kept, with their times.
    let first_eval = &stopped["evals"][0];
    assert!(
        summary["evals"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e == first_eval),
        "{first_eval} missing from {:#}",
        summary["evals"]
    );
}
