//! Replays the `rpc_decode` fuzz corpus and every crash reproducer (`fuzz/corpus/rpc_decode/`,
//! `fuzz/artifacts/rpc_decode/`) through the fuzz target's own body, `fuzz/harness/rpc_decode.rs`,
//! on stable Rust without libFuzzer (docs/FUZZING.md).
use std::path::{Path, PathBuf};

#[path = "../../fuzz/harness/rpc_decode.rs"]
mod harness;

const TARGET: &str = "rpc_decode";

#[path = "../../fuzz/harness/replay.rs"]
mod replay;

fn inputs(kind: &str) -> Vec<PathBuf> {
    replay::inputs(env!("CARGO_MANIFEST_DIR"), kind, TARGET)
}

/// Whether a rejection says which message was refused and why: `convert`'s errors name
/// `Message.field` (the message may be nested: a `ResetLease`'s `ResetArgs`), prost's name the
/// decode failure (the harness prefixes the message type), the token's name the token.
fn names_what_was_wrong(r: &str) -> bool {
    let Some((message, why)) = r.split_once(": ") else {
        return false;
    };
    let names_field = why.strip_prefix("malformed ").is_some_and(|rest| {
        rest.split_once(": ").is_some_and(|(path, problem)| {
            path.split_once('.').is_some_and(|(m, f)| {
                m.chars().all(|c| c.is_ascii_alphanumeric())
                    && !m.is_empty()
                    && f.chars().all(|c| c.is_ascii_lowercase() || c == '_')
                    && !f.is_empty()
            }) && !problem.is_empty()
        })
    });
    !message.is_empty()
        && (why.starts_with("failed to decode Protobuf message")
            || names_field
            || (message == "TransitionBatch" && why.starts_with("records: transition batch"))
            || (message == "authorization token" && why.contains("run token")))
}

fn replay(files: &[PathBuf]) -> usize {
    replay::replay(files, harness::run, names_what_was_wrong)
}

#[test]
fn rpc_decode_corpus_replays_without_panics() {
    let corpus = inputs("corpus");
    replay::non_empty(TARGET, &corpus, 5);
    let rejections = replay(&corpus);
    assert!(rejections > 0, "the corpus exercises no rejection at all");
}

#[test]
fn rpc_decode_crash_reproducers_stay_fixed() {
    replay(&inputs("artifacts"));
}

/// Rewrites the seed inputs of the corpus (`cargo test -p rfcl-proto --test fuzz_regressions --
/// --ignored write_seed_corpus`): one valid encoding of each message kind; `cargo fuzz cmin` then
/// keeps what adds coverage.
#[test]
#[ignore = "writes fuzz/corpus/rpc_decode/seed-*: run by hand"]
fn write_seed_corpus() {
    use prost::Message;
    use rfcl_proto::v1;
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/corpus")
        .join(TARGET);
    std::fs::create_dir_all(&dir).unwrap();
    let report = v1::EpisodeReport {
        lease_id: 7,
        success_at_end: true,
        success_once: true,
        episode_return: 1.5,
        length: 40,
        policy_version: 3,
        stage_epoch: 1,
        actor_id: 2,
        actor_env_steps: 4000,
        policy_env_steps: 3900,
        actor_sim_restarts: 1,
        reset_failure: String::new(),
    };
    let acquire = v1::AcquireRequest {
        actor_id: 2,
        env_index: 1,
        eval: true,
    };
    let lease = v1::ResetLease {
        lease_id: 9,
        kind: v1::LeaseKind::DemoState as i32,
        demo_id: 1,
        start_index: 12,
        env_state: vec![0.5, -1.0, 2.0],
        reset: Some(v1::ResetArgs {
            has_seed: true,
            seed: 42,
            options_json: r#"{"reconfigure": true, "goal": [1.5, -2e-3]}"#.into(),
        }),
        time_limit: 50,
        stage_epoch: 1,
        stage: 1,
        level: 0,
    };
    // One record of obs_dim 2, action_dim 1: 32 + 4 × 5 = 52, padded to 56 bytes.
    let batch = v1::TransitionBatch {
        actor_id: 2,
        obs_dim: 2,
        action_dim: 1,
        count: 1,
        records: vec![0; 56],
    };
    let seeds: Vec<(&str, Vec<u8>)> = vec![
        ("seed-acquire", acquire.encode_to_vec()),
        ("seed-report", report.encode_to_vec()),
        (
            "seed-report-and-acquire",
            v1::ReportAndAcquireRequest {
                report: Some(report),
                next: Some(acquire),
            }
            .encode_to_vec(),
        ),
        ("seed-lease", lease.clone().encode_to_vec()),
        (
            "seed-reply",
            v1::ReportAndAcquireReply {
                ack: Some(v1::ReportAck {
                    applied: true,
                    stage: 1,
                    stage_epoch: 0,
                }),
                lease: Some(lease),
            }
            .encode_to_vec(),
        ),
        (
            "seed-run-info",
            v1::RunInfo {
                run_name: "pointmaze".into(),
                obs_dim: 2,
                action_dim: 2,
                action_scale: vec![0.5, 2.0],
                transport: "shm".into(),
                ..Default::default()
            }
            .encode_to_vec(),
        ),
        ("seed-batch", batch.encode_to_vec()),
        (
            "seed-get-run-info",
            v1::GetRunInfoRequest {
                actor_id: 1,
                hostname: "actor-0".into(),
                host_identity: "machine boot shm".into(),
            }
            .encode_to_vec(),
        ),
        (
            "seed-watch-policy",
            v1::WatchPolicyRequest { after_version: 12 }.encode_to_vec(),
        ),
        (
            "seed-authorization",
            b"Bearer 0123456789abcdef0123456789abcdef".to_vec(),
        ),
    ];
    for (name, bytes) in seeds {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
}
