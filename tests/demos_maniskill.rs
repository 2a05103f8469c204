//! The hard ManiSkill3 tasks' demos, made and checked as a user makes and checks them:
//! `rfcl demos generate --env TASK -n 1` (ManiSkill's motion planner, then its replay into
//! pd_joint_delta_pos) and `rfcl demos inspect --replay --config <the task's preset>` (every state
//! restores exactly, every step replays with positions and orientations within their tolerances
//! and its success flag, the last step ends in a success). Seeds the planner gives no successful
//! episode for are named as skipped and never written.
//!
//! One short test per task: 20-30 s for StackCube and PlugCharger, about a minute for
//! PegInsertionSide, whose every reset rebuilds its scene (~170 ms) on the 2-core development
//! machine.
use std::collections::BTreeSet;
use std::path::Path;
use std::process::Command;

use rfcl_core::demo::DemoSet;
use rfcl_testkit::hdf5::fork_guard;

fn rfcl(args: &[&str]) -> (bool, String) {
    rfcl_testkit::child::outcome(Command::new(env!("CARGO_BIN_EXE_rfcl")).args(args))
}

/// The seeds in `{a, b}` after `marker` on the line that holds it.
fn seeds_after(text: &str, marker: &str) -> BTreeSet<u64> {
    let Some(line) = text.lines().find(|l| l.contains(marker)) else {
        return BTreeSet::new();
    };
    let list = line.split(marker).nth(1).unwrap();
    let list = &list[list.find(['{', '[']).unwrap() + 1..list.find(['}', ']']).unwrap()];
    list.split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|s| s.trim().parse().unwrap())
        .collect()
}

fn generate_and_replay(env: &str, preset: &str) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("demos.h5");
    let file_s = file.to_str().unwrap();
    let (ok, log) = rfcl(&[
        "demos", "generate", "--env", env, "-n", "1", "--out", file_s,
    ]);
    assert!(ok, "{log}");
    let written = seeds_after(&log, "seeds ");
    assert_eq!(written.len(), 1, "{log}");
    let first = *written.first().unwrap();
    // Every seed before the written one gave no demo, and is named as skipped.
    let skipped = seeds_after(&log, "no successful episode for ");
    let replays = seeds_after(&log, "did not replay to a success");
    let named: BTreeSet<u64> = skipped.union(&replays).copied().collect();
    assert_eq!(named, (0..first).collect(), "{log}");
    {
        let _guard = fork_guard();
        let set = DemoSet::load(&file).unwrap();
        assert_eq!(set.demos.len(), 1);
        assert_eq!(set.demos[0].reset.seed, Some(first));
        assert!(set.demos[0].succeeded);
    }

    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join(preset);
    let (ok, report) = rfcl(&[
        "demos",
        "inspect",
        file_s,
        "--replay",
        "--config",
        config.to_str().unwrap(),
    ]);
    assert!(ok, "{report}");
    rfcl_testkit::assert_contains_all(
        &report,
        &[
            "1 of 1 demos pass the replay check",
            "states restore exactly, one-step errors: orientation",
        ],
    );
}

#[test]
fn stack_cube_demo_generates_and_replays() {
    generate_and_replay("StackCube-v1", "configs/maniskill3/stack_cube.yml");
}

#[test]
fn peg_insertion_side_demo_generates_and_replays() {
    generate_and_replay(
        "PegInsertionSide-v1",
        "configs/maniskill3/peg_insertion_side.yml",
    );
}

#[test]
fn plug_charger_demo_generates_and_replays() {
    generate_and_replay("PlugCharger-v1", "configs/maniskill3/plug_charger.yml");
}
