//! cargo-fuzz target `demo_hdf5`: the body is fuzz/harness/demo_hdf5.rs, which the crate's regression test
//! (tests/fuzz_regressions.rs) includes too, so a saved input replays exactly as fuzzed.
#![no_main]

#[path = "../harness/demo_hdf5.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = harness::run(data);
});
