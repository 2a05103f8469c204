//! Per-demo difficulty on a real run (docs/ALGORITHM.md 2.10): one of 5 generated PointMaze demos is
//! made deliberately bad (the first half of its states moved to the start cell farthest from the
//! goal, so that from there no episode reaches the goal within the demo's dynamic time limit). The
//! run's curriculum flags that demo, and only it, as stalled, at the state where its reachable part
//! ends and in the far cell, while every other demo's frontier reaches its first state;
//! `rfcl demos select` then writes the file without it, from the running run and from the stopped
//! run's summary, and a run on the best demo it keeps ends with stage 1 (`stage_1_done`).
//!
//! About 3-5 minutes on the 2-core development machine.
mod train_support;

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use rfcl_core::demo::DemoSet;
use rfcl_core::maze::{cell_at, cell_centre, maze};
use rfcl_testkit::demos::write_demo_set;
use rfcl_testkit::hdf5::fork_guard;
use train_support::*;

/// PointMaze's state layout (qpos, qvel, collided) and the test config's reverse step δ.
const STATE_DIM: usize = 5;
const STEP_SIZE: u64 = 8;

/// A bad copy of `good` at `bad`: the shortest demo's first half of states moved to the start cell
/// farthest from the goal, at rest. Returns its episode id, the first state left in place, and the
/// far cell.
fn write_bad_demos(good: &Path, bad: &Path) -> (u64, usize, [u64; 2]) {
    let mut set = {
        let _guard = fork_guard();
        DemoSet::load(good).unwrap()
    };
    assert_eq!(set.state_dim, STATE_DIM);
    let m = maze();
    let far = *m
        .start_cells()
        .iter()
        .max_by_key(|&&c| m.distance_to_goal(c))
        .unwrap();
    let demo = set.demos.iter_mut().min_by_key(|d| d.len()).unwrap();
    let boundary = demo.len().div_ceil(2);
    let [x, y] = cell_centre(far);
    for state in demo.env_states[..boundary * STATE_DIM].chunks_exact_mut(STATE_DIM) {
        state[..4].copy_from_slice(&[x, y, 0.0, 0.0]);
    }
    // Far indeed: the demo's own first state is much nearer the goal.
    let own = cell_at([
        demo.env_states[boundary * STATE_DIM],
        demo.env_states[boundary * STATE_DIM + 1],
    ])
    .unwrap();
    assert!(m.distance_to_goal(far).unwrap() > m.distance_to_goal(own).unwrap() + 10);
    let id = demo.episode_id;
    write_demo_set(&set, bad);
    (id, boundary, [far.0 as u64, far.1 as u64])
}

/// `rfcl demos select FILE --run RUN_DIR --out OUT [extra]`: (success, stdout + stderr).
fn select(file: &Path, run_dir: &Path, out: &Path, extra: &[&str]) -> (bool, String) {
    rfcl_testkit::child::outcome(
        Command::new(env!("CARGO_BIN_EXE_rfcl"))
            .args(["demos", "select"])
            .arg(file)
            .arg("--run")
            .arg(run_dir)
            .arg("--out")
            .arg(out)
            .args(extra),
    )
}

fn episode_ids(file: &Path) -> Vec<u64> {
    let _guard = fork_guard();
    let mut ids: Vec<u64> = DemoSet::load(file)
        .unwrap()
        .demos
        .iter()
        .map(|d| d.episode_id)
        .collect();
    ids.sort();
    ids
}

#[test]
fn a_demo_with_an_unreachable_part_is_the_only_one_flagged_and_select_drops_it() {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let good = generate_demos(dir.path());
    let bad = dir.path().join("bad.h5");
    let (bad_id, boundary, far) = write_bad_demos(&good, &bad);
    // The quality check finds it with no run: its actions do not replay into its states.
    let out = Command::new(env!("CARGO_BIN_EXE_rfcl"))
        .args(["demos", "inspect", "--replay"])
        .arg(&bad)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{text}");
    assert!(
        text.contains(&format!("(episode {bad_id}): FAILED: one step from state")),
        "{text}"
    );
    assert!(text.contains("4 of 5 demos pass"), "{text}");
    let run_dir = dir.path().join("run");
    let mut training = start_run(
        &test_config(),
        &bad,
        &[
            "service.stop_at_eval_success=null".into(),
            "service.stall_after_env_steps=20000".into(),
        ],
        &run_dir,
        &dir.path().join("rfcl.stderr"),
    );
    let processes = training.processes(Duration::from_secs(120));

    // Until the bad demo is flagged and every other frontier has reached its first state.
    let state = wait_for(Duration::from_secs(900), || {
        let state = curriculum_state(&processes)?;
        let demos = state["demos"].as_array()?;
        let bad_flagged = demos
            .iter()
            .any(|d| d["episode_id"] == bad_id && d["difficulty"]["stalled"] == true);
        let others_at_start = demos
            .iter()
            .filter(|d| d["episode_id"] != bad_id)
            .all(|d| d["t"] == 0);
        (bad_flagged && others_at_start).then_some(state)
    })
    .unwrap_or_else(|| {
        panic!(
            "the bad demo was not flagged with the others at their first state:\n{:#}\n{}",
            curriculum_state(&processes).unwrap_or_default()["demos"],
            training.stderr()
        )
    });
    let demos = state["demos"].as_array().unwrap();
    assert_eq!(demos.len(), 5);
    let flagged: Vec<u64> = demos
        .iter()
        .filter(|d| d["difficulty"]["stalled"] == true)
        .map(|d| d["episode_id"].as_u64().unwrap())
        .collect();
    assert_eq!(flagged, vec![bad_id], "{:#}", state["demos"]);
    let stalled = demos.iter().find(|d| d["episode_id"] == bad_id).unwrap();
    // It stalls at the first frontier below the states left in place, in the far cell, having
    // moved there at some speed, and no episode from its frontier succeeds any more.
    let t = stalled["t"].as_u64().unwrap();
    assert!(
        t < boundary as u64 && t + STEP_SIZE >= boundary as u64,
        "stalled at {t}, the reachable part starts at {boundary}"
    );
    let x = &stalled["difficulty"];
    assert_eq!(x["cell"], serde_json::json!(far), "{stalled:#}");
    assert!(x["speed"].as_f64().unwrap() > 0.0, "{stalled:#}");
    assert!(
        x["env_steps_since_move"].as_u64().unwrap() >= 20_000,
        "{stalled:#}"
    );
    assert!(x["frontier_episodes"].as_u64().unwrap() > 0, "{stalled:#}");

    // Select from the running run: its curriculum server answers.
    let selected = dir.path().join("selected.h5");
    let (ok, text) = select(&bad, &run_dir, &selected, &[]);
    assert!(ok, "{text}");
    assert!(text.contains("curriculum server at"), "{text}");
    assert!(
        text.contains(&format!(
            "dropped episode {bad_id}: stalled at state {t} of"
        )),
        "{text}"
    );
    assert!(text.contains("kept 4 of the run's 5 demos"), "{text}");
    let mut expected: Vec<u64> = episode_ids(&good)
        .into_iter()
        .filter(|&id| id != bad_id)
        .collect();
    expected.sort();
    assert_eq!(episode_ids(&selected), expected);

    // Stopped, the summary keeps the flags, and select reads them there.
    signal(training.pid(), rustix::process::Signal::TERM);
    training.wait(Duration::from_secs(120));
    let summary = training.summary();
    assert_eq!(summary["ending"], "interrupted", "{summary:#}");
    let flagged: Vec<&serde_json::Value> = summary["demos"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|d| d["difficulty"]["stalled"] == true)
        .map(|d| &d["episode_id"])
        .collect();
    assert_eq!(flagged, vec![&serde_json::json!(bad_id)], "{summary:#}");
    let best = dir.path().join("best.h5");
    let (ok, text) = select(&bad, &run_dir, &best, &["--best", "1"]);
    assert!(ok, "{text}");
    assert!(text.contains("summary.json"), "{text}");
    assert!(text.contains("not among the best 1"), "{text}");
    assert_eq!(episode_ids(&best).len(), 1);

    // One good demo: stage 1 ends, and so does a stage_1_only run (long reverse steps keep it
    // short).
    let best_dir = dir.path().join("best-run");
    let overrides = [
        "train.num_demos=1",
        "train.stage_1_only=true",
        "reverse.reverse_step_size=32",
        "service.stop_at_eval_success=null",
    ]
    .map(String::from);
    let log = dir.path().join("best.stderr");
    let mut training = start_run(&test_config(), &best, &overrides, &best_dir, &log);
    let status = training.wait(Duration::from_secs(600));
    assert!(status.success(), "{status:?}\n{}", training.stderr());
    let summary = training.summary();
    assert_eq!(summary["ending"], "stage_1_done", "{summary:#}");
    assert!(
        summary["stage_1_env_steps"].as_u64().is_some(),
        "{summary:#}"
    );
    assert_eq!(summary["demos"][0]["solved"], true, "{summary:#}");
}
