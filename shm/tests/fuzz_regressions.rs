//! Replays the `shm_frame` fuzz corpus and every crash reproducer (`fuzz/corpus/shm_frame/`,
//! `fuzz/artifacts/shm_frame/`) through the fuzz target's own body, `fuzz/harness/shm_frame.rs`,
//! on stable Rust without libFuzzer (docs/FUZZING.md).
use std::path::{Path, PathBuf};

#[path = "../../fuzz/harness/shm_frame.rs"]
mod harness;

const TARGET: &str = "shm_frame";

#[path = "../../fuzz/harness/replay.rs"]
mod replay;

fn inputs(kind: &str) -> Vec<PathBuf> {
    replay::inputs(env!("CARGO_MANIFEST_DIR"), kind, TARGET)
}

/// A frame rejection says which kind of frame it refused.
fn names_the_frame(r: &str) -> bool {
    r.contains("frame") && (r.contains("transition") || r.contains("policy"))
}

fn replay(files: &[PathBuf]) {
    replay::replay(files, harness::run, names_the_frame);
}

#[test]
fn shm_frame_corpus_replays_without_panics() {
    let corpus = inputs("corpus");
    replay::non_empty(TARGET, &corpus, 3);
    replay(&corpus);
}

#[test]
fn shm_frame_crash_reproducers_stay_fixed() {
    replay(&inputs("artifacts"));
}

/// Rewrites the seed inputs of the corpus (`cargo test -p rfcl-shm --test fuzz_regressions --
/// --ignored write_seed_corpus`); `cargo fuzz cmin` then keeps what adds coverage.
#[test]
#[ignore = "writes fuzz/corpus/shm_frame/seed-*: run by hand"]
fn write_seed_corpus() {
    use rfcl_shm::frame::{
        PolicyHeader, TransitionHeader, POLICY_HEADER_BYTES, TRANSITION_HEADER_BYTES,
    };
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/corpus")
        .join(TARGET);
    std::fs::create_dir_all(&dir).unwrap();
    let header = TransitionHeader {
        actor_id: 3,
        obs_dim: 2,
        action_dim: 1,
        count: 1,
        publisher: 0x0123_4567_89AB_CDEF,
        seq: 5,
        records_before: 5,
    };
    let mut transition = vec![0x3F; TRANSITION_HEADER_BYTES + 56];
    header.encode(&mut transition);
    let mut policy = vec![b'{'; POLICY_HEADER_BYTES + 16];
    PolicyHeader {
        version: 4,
        learner_env_steps: 1000,
    }
    .encode(&mut policy);
    let mut header_only = vec![0; TRANSITION_HEADER_BYTES];
    TransitionHeader::default().encode(&mut header_only);
    for (name, bytes) in [
        ("seed-transition", transition),
        ("seed-policy", policy),
        ("seed-transition-header-only", header_only),
        ("seed-short", b"RFCT\x01\x00".to_vec()),
    ] {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
}
