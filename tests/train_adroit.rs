//! Adroit end to end, with the real simulator and real processes: a small Door file in D4RL's
//! format (tests/adroit_d4rl.py: 2 episodes that start with the door open, so they succeed) is
//! converted by `rfcl demos convert`, then a short `rfcl train configs/adroit/door.yml` (tiny
//! networks, a few thousand env steps) runs in which the curriculum server, the learner, both
//! actors (each with a Python worker) and the eval actor take part and the learner receives the
//! transitions; no process outlives the run.
mod train_support;

use std::path::{Path, PathBuf};
use std::process::Command;

use train_support::*;

fn rfcl() -> &'static str {
    env!("CARGO_BIN_EXE_rfcl")
}

/// 2 successful Door demos: a D4RL-format file written by tests/adroit_d4rl.py, converted by
/// `rfcl demos convert` (suite and task from the file name, door-human-v1.hdf5).
fn converted_door_demos(dir: &Path) -> PathBuf {
    let src = dir.join("door-human-v1.hdf5");
    rfcl_testkit::demos::write_d4rl_door(&src, 2, 0, 16);
    let out = dir.join("door.h5");
    let result = Command::new(rfcl())
        .args(["demos", "convert"])
        .arg(&src)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&result.stderr);
    assert!(result.status.success(), "rfcl demos convert failed: {log}");
    assert!(
        log.contains("converted 2 AdroitHandDoorSparse-v1 demos (2 successful"),
        "{log}"
    );
    out
}

#[test]
fn door_smoke_run_uses_every_process() {
    let dir = tempfile::tempdir().unwrap();
    let demos = converted_door_demos(dir.path());
    sim::smoke_run(
        "configs/adroit/door.yml",
        &demos,
        dir.path(),
        "AdroitHandDoorSparse-v1",
        200,
    );
}
