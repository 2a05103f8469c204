//! The curriculum server SIGKILLed and then the learner hung (SIGSTOP) in the middle of a run:
//! `rfcl train` kills the silent learner at `service.hang_timeout_s`, restarts each on its port
//! from its last snapshot or checkpoint, says so with what was rolled back, the actors and the
//! other service reconnect by themselves, and the run still reaches its bar (train_support's
//! [`BAR`]). The summary lists both restarts with their causes.
mod train_support;

use std::time::Duration;

use train_support::*;

/// The processes.json of the run once `name` has a pid other than `old`.
fn replaced(run_dir: &std::path::Path, name: &str, old: u64) -> Option<(u64, serde_json::Value)> {
    let p: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run_dir.join("processes.json")).ok()?)
            .ok()?;
    let pid = child_pid(&p, name);
    (pid != old).then_some((pid, p))
}

#[test]
fn killed_services_are_restarted_and_the_run_reaches_its_bar() {
    let dir = tempfile::tempdir().unwrap();
    let mut training = start_test_run(
        dir.path(),
        &[
            stop_at_bar(),
            // Snapshots and checkpoints often enough that each kill rolls back little.
            "service.snapshot_every_s=2".into(),
            "sac.save_every_s=10".into(),
            "service.hang_timeout_s=10".into(),
        ],
        "rfcl.stderr",
    );
    let run_dir = training.run_dir.clone();
    let processes = training.processes(Duration::from_secs(120));

    // The curriculum server, once episodes are being reported.
    wait_for(Duration::from_secs(180), || {
        (curriculum_state(&processes)?["episodes"].as_u64()? > 50).then_some(())
    })
    .unwrap_or_else(|| panic!("no episodes:\n{}", training.stderr()));
    let server = child_pid(&processes, "curriculum-server");
    signal(server as u32, rustix::process::Signal::KILL);
    let (new_server, processes) = wait_for(Duration::from_secs(60), || {
        replaced(&run_dir, "curriculum-server", server)
    })
    .unwrap_or_else(|| {
        panic!(
            "the curriculum server was not restarted:\n{}",
            training.stderr()
        )
    });
    assert!(alive(new_server));
    let stderr = training.stderr();
    assert!(
        stderr.contains("the curriculum-server died (killed by signal 9); restarting it"),
        "{stderr}"
    );
    // On the same address, so the learner and the actors find it: reports flow again.
    let episodes = wait_for(Duration::from_secs(30), || {
        curriculum_state(&processes)?["episodes"].as_u64()
    })
    .unwrap_or_else(|| panic!("the new server does not answer:\n{}", training.stderr()));
    wait_for(Duration::from_secs(120), || {
        (curriculum_state(&processes)?["episodes"].as_u64()? > episodes + 20).then_some(())
    })
    .unwrap_or_else(|| panic!("no reports after the restart:\n{}", training.stderr()));

    // Then the learner, once it has taken in more env steps.
    let learner = child_pid(&processes, "learner");
    wait_for(Duration::from_secs(180), || {
        (learner_health(&processes)?.env_steps > 15_000).then_some(())
    })
    .unwrap_or_else(|| panic!("the learner made no progress:\n{}", training.stderr()));
    signal(learner as u32, rustix::process::Signal::STOP);
    let (new_learner, processes) = wait_for(Duration::from_secs(120), || {
        replaced(&run_dir, "learner", learner)
    })
    .unwrap_or_else(|| panic!("the hung learner was not restarted:\n{}", training.stderr()));
    assert!(alive(new_learner));
    let stderr = training.stderr();
    assert!(
        stderr.contains(&format!(
            "the learner (pid {learner}) has not answered for 1"
        )) && stderr.contains("killing it to restart it")
            && stderr.contains("the learner died (killed after not answering for 1"),
        "{stderr}"
    );

    let status = training.wait(Duration::from_secs(900));
    assert!(status.success(), "{status}:\n{}", training.stderr());
    let summary = training.summary();
    assert_reached(&summary, BAR);
    let restarts = summary["service_restarts"].as_array().unwrap();
    let processes_restarted: Vec<&str> = restarts
        .iter()
        .map(|r| r["process"].as_str().unwrap())
        .collect();
    assert_eq!(
        processes_restarted,
        ["curriculum-server", "learner"],
        "{summary}"
    );
    assert_eq!(restarts[0]["cause"], "killed by signal 9");
    assert!(
        restarts[1]["cause"]
            .as_str()
            .unwrap()
            .starts_with("killed after not answering for 1"),
        "{summary}"
    );
    for r in restarts {
        assert!(r["rolled_back"]["env_steps"].is_u64());
    }
    for pid in child_pids(&processes) {
        assert!(!alive(pid), "child {pid} outlived the run");
    }
}
