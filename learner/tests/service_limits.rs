//! Request size limits of the learner's gRPC service: a request larger than the largest
//! `TransitionBatch` of `service.transition_batch` records (2× margin, plus 64 KiB) is refused
//! (a batch RESOURCE_EXHAUSTED and counted; a unary request by tonic), and the learner keeps
//! serving.
mod service_support;

use std::time::Duration;

use rfcl_core::transition::RecordLayout;
use rfcl_learner::service::max_request_bytes;
use rfcl_proto::v1;
use service_support::*;

const W: u64 = 8;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversized_requests_are_refused_and_the_learner_keeps_serving() {
    let dir = tempfile::tempdir().unwrap();
    let demos = write_demos(dir.path());
    let config = write_config(dir.path(), W, 100_000, "");
    let run_dir = dir.path().join("run");
    let curriculum = Curriculum::start(&config, &demos, &run_dir);
    let args = Learner::args(&config, &curriculum.grpc, &demos, &run_dir);
    let args: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    let learner = Learner::start(&args);
    let mut client = learner.client().await;
    let layout = RecordLayout::new(OBS, ACT);
    // The test config keeps the default service.transition_batch, 64.
    let limit = max_request_bytes(layout, 64);
    assert!(limit < 1 << 20, "{limit} B");

    // A batch of one record more than the limit holds.
    let rows = limit / layout.record_bytes() + 1;
    assert!(rows * layout.record_bytes() > limit);
    let err = push(&mut client, batches(0..rows as u64, rows, 0))
        .await
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::ResourceExhausted, "{err}");

    assert!(
        err.message().contains("service.transition_batch = 64"),
        "{err}"
    );

    // A unary request far larger than any real one (a 2 MB host name): tonic refuses it before
    // the handler (OUT_OF_RANGE, its code for a message over the limit).
    let err = client
        .get_run_info(v1::GetRunInfoRequest {
            actor_id: 1,
            hostname: "h".repeat(2 << 20),
            host_identity: String::new(),
        })
        .await
        .unwrap_err();
    assert!(
        matches!(
            err.code(),
            tonic::Code::OutOfRange | tonic::Code::ResourceExhausted
        ) && err.message().contains("too large"),
        "{err}"
    );

    // Still serving: health, run info, and batches of the configured size (up to twice it).
    let h = health(&mut client).await;
    assert!(h.ok);
    assert_eq!((h.env_steps, h.refused_batches), (0, 1));
    client
        .get_run_info(v1::GetRunInfoRequest {
            actor_id: 1,
            hostname: "test".into(),
            host_identity: String::new(),
        })
        .await
        .unwrap();
    let summary = push(&mut client, batches(0..192, 128, 0)).await.unwrap();
    assert_eq!(summary.accepted, 192);
    wait_health(&mut client, Duration::from_secs(60), |h| h.env_steps == 192).await;
}
