//! MetaWorld end to end, with the real simulator and real processes: 2 scripted pick-place-v3
//! demos from `rfcl demos generate --env metaworld/pick-place-v3`, then a short `rfcl train
//! configs/metaworld/pick_place.yml` (tiny networks, a few thousand env steps) in which the
//! curriculum server, the learner, both actors (each with a Python worker) and the eval actor take
//! part and the learner receives the transitions; no process outlives the run.
mod train_support;

use std::path::{Path, PathBuf};
use std::process::Command;

use train_support::*;

fn rfcl() -> &'static str {
    env!("CARGO_BIN_EXE_rfcl")
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

#[test]
fn pick_place_smoke_run_uses_every_process() {
    let dir = tempfile::tempdir().unwrap();
    let demos = generate_pick_place(dir.path(), 2);
    sim::smoke_run(
        "configs/metaworld/pick_place.yml",
        &demos,
        dir.path(),
        "pick-place-v3",
        200,
    );
}
