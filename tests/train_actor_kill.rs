//! A train actor SIGKILLed in the middle of a run: `rfcl train` respawns it and says so, the
//! leases it held expire on the curriculum server and are counted, and the run still reaches its
//! bar (train_support's [`BAR`]).
mod train_support;

use std::time::Duration;

use train_support::*;

/// Short enough that the dead actor's leases expire well before the run ends, long enough for any
/// live episode (300 steps) on a loaded machine.
const LEASE_TIMEOUT_S: u64 = 20;
#[test]
fn a_killed_actor_is_respawned_and_its_leases_expire() {
    let dir = tempfile::tempdir().unwrap();
    let mut training = start_test_run(
        dir.path(),
        &[
            format!("service.lease_timeout_s={LEASE_TIMEOUT_S}"),
            stop_at_bar(),
        ],
        "rfcl.stderr",
    );
    let run_dir = training.run_dir.clone();
    let processes = training.processes(Duration::from_secs(120));
    let victim = child_pid(&processes, "actor-0");

    // Once actor 0 is working (it holds a lease per env), kill it without warning.
    let held = wait_for(Duration::from_secs(120), || {
        let state = curriculum_state(&processes)?;
        let row = state["actors"]
            .as_array()?
            .iter()
            .find(|a| a["actor_id"] == 0)?
            .clone();
        (row["env_steps"].as_u64()? > 2000 && row["open_leases"].as_u64()? > 0)
            .then(|| (row["open_leases"].as_u64().unwrap(), state))
    });
    let (open, before) =
        held.unwrap_or_else(|| panic!("actor 0 never ran:\n{}", training.stderr()));
    let expired_before = before["expired_leases"].as_u64().unwrap();
    signal(victim as u32, rustix::process::Signal::KILL);

    // rfcl notices, says so and starts a new actor 0.
    let respawned = wait_for(Duration::from_secs(30), || {
        let p = serde_json::from_str::<serde_json::Value>(
            &std::fs::read_to_string(run_dir.join("processes.json")).ok()?,
        )
        .ok()?;
        let pid = child_pid(&p, "actor-0");
        (pid != victim).then_some(pid)
    })
    .unwrap_or_else(|| panic!("actor 0 was not respawned:\n{}", training.stderr()));
    assert!(alive(respawned));
    training.wait_for_stderr(
        &format!("actor-0 died (killed by signal 9); respawned it (pid {respawned})"),
        Duration::from_secs(10),
    );

    // The leases the dead actor held expire after the timeout and are counted.
    let expired = wait_for(Duration::from_secs(LEASE_TIMEOUT_S + 60), || {
        let state = curriculum_state(&processes)?;
        let expired = state["expired_leases"].as_u64()?;
        (expired > expired_before).then_some(expired)
    })
    .unwrap_or_else(|| panic!("no lease expired:\n{}", training.stderr()));
    assert!(expired > expired_before);
    assert!(open >= 1);

    let status = training.wait(Duration::from_secs(900));
    assert!(status.success(), "{status}:\n{}", training.stderr());
    let summary = training.summary();
    assert_reached(&summary, BAR);
    assert!(summary["actor_respawns"].as_u64().unwrap() >= 1);
    assert!(summary["expired_leases"].as_u64().unwrap() >= expired);
    for pid in child_pids(&processes).into_iter().chain([respawned]) {
        assert!(!alive(pid), "child {pid} outlived the run");
    }
}
