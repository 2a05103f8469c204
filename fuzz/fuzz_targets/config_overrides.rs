//! cargo-fuzz target `config_overrides`: the body is fuzz/harness/config_overrides.rs, which the crate's regression test
//! (tests/fuzz_regressions.rs) includes too, so a saved input replays exactly as fuzzed.
#![no_main]

#[path = "../harness/config_overrides.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = harness::run(data);
});
