//! cargo-fuzz target `rpc_decode`: the body is fuzz/harness/rpc_decode.rs, which the crate's regression test
//! (tests/fuzz_regressions.rs) includes too, so a saved input replays exactly as fuzzed.
#![no_main]

#[path = "../harness/rpc_decode.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = harness::run(data);
});
