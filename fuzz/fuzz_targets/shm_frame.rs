//! cargo-fuzz target `shm_frame`: the body is fuzz/harness/shm_frame.rs, which the crate's regression test
//! (tests/fuzz_regressions.rs) includes too, so a saved input replays exactly as fuzzed.
#![no_main]

#[path = "../harness/shm_frame.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = harness::run(data);
});
