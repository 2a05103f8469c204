//! Fuzz body of `demo_hdf5`: the HDF5 demo reader (`rfcl_core::demo::DemoSet::load`, what `rfcl
//! train` and `rfcl demos inspect` run on a dataset path) on arbitrary file contents. Shared by
//! `fuzz/fuzz_targets/demo_hdf5.rs` and `core/tests/fuzz_regressions.rs` (included by `#[path]`).
//!
//! The input is written to `demo.h5` in a fresh temporary directory (no JSON sidecar beside it)
//! and loaded. The seeds in `fuzz/corpus/demo_hdf5/` are small valid files in each `env_states`
//! form, written by `DemoSet::write`.
//!
//! Properties: no panic, no abort; a refusal is a `DemoError` whose message names the file; an
//! accepted set is consistent (every row of every demo is in range), summarises, and selects.
use rfcl_core::demo::DemoSet;

/// Loads the input as a demo file; returns the refusal's message, if any.
pub fn run(data: &[u8]) -> Vec<String> {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let path = dir.path().join("demo.h5");
    std::fs::write(&path, data).expect("writing the demo file");
    match DemoSet::load(&path) {
        Ok(set) => {
            check(&set);
            Vec::new()
        }
        Err(e) => vec![e.to_string()],
    }
}

fn check(set: &DemoSet) {
    assert!(!set.demos.is_empty());
    assert_eq!(set.state_dim, set.state_layout.dim());
    for demo in &set.demos {
        assert_eq!(demo.obs_dim, set.obs_dim);
        assert_eq!(demo.action_dim, set.action_dim);
        assert_eq!(demo.state_dim, set.state_dim);
        let t = demo.len();
        assert_eq!(demo.obs.len(), (t + 1) * demo.obs_dim);
        assert_eq!(demo.actions.len(), t * demo.action_dim);
        assert_eq!(demo.env_states.len(), (t + 1) * demo.state_dim);
        for s in 0..demo.num_states() {
            assert!(demo.obs_row(s).iter().all(|x| x.is_finite()));
            assert!(demo.state_row(s).iter().all(|x| x.is_finite()));
        }
        for a in 0..t {
            assert!(demo.action_row(a).iter().all(|x| x.is_finite()));
        }
    }
    let _ = set.summary();
    let _ = set.select(1, true, 7);
}
