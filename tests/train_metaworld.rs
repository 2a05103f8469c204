//! MetaWorld end to end, with the real simulator and real processes: 2 scripted pick-place-v3
//! demos from `rfcl demos generate --env metaworld/pick-place-v3`, then a short `rfcl train
//! configs/metaworld/pick_place.yml` (tiny networks, a few thousand env steps) in which the
//! curriculum server, the learner, both actors (each with a Python worker) and the eval actor take
//! part and the learner receives the transitions; no process outlives the run.
mod train_support;

use train_support::*;

#[test]
fn pick_place_smoke_run_uses_every_process() {
    let dir = tempfile::tempdir().unwrap();
    let demos = generate_env_demos(
        "metaworld/pick-place-v3",
        2,
        &dir.path().join("pick_place.h5"),
    );
    sim::smoke_run(
        "configs/metaworld/pick_place.yml",
        &demos,
        dir.path(),
        "pick-place-v3",
        200,
    );
}
