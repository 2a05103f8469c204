//! SIGTERM while clients hold streams open: actors watching policy versions (WatchPolicy) and an
//! actor in the middle of a PushTransitions stream. The learner must still stop within seconds,
//! with its final checkpoint and exported policy, and end the streams rather than leave them
//! hanging.
mod service_support;

use std::time::{Duration, Instant};

use rfcl_proto::v1;
use service_support::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_with_open_streams_stops_in_seconds_and_ends_them() {
    let dir = tempfile::tempdir().unwrap();
    let run_dir = dir.path().join("run");
    let demos = write_demos(dir.path());
    let config = write_config(dir.path(), 8, 100_000, "");
    let curriculum = Curriculum::start(&config, &demos, &run_dir);
    let args = Learner::args(&config, &curriculum.grpc, &demos, &run_dir);
    let args: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    let mut learner = Learner::start(&args);
    let mut client = learner.client().await;

    // Three subscribers, each holding the initial version and waiting for the next.
    let mut watchers = Vec::new();
    for _ in 0..3 {
        let mut watch = client
            .watch_policy(v1::WatchPolicyRequest { after_version: 0 })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(watch.message().await.unwrap().unwrap().version, 1);
        watchers.push(watch);
    }
    // A transition stream whose sender stays open: one batch in, then nothing.
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(batches(0..4, 4, 0).remove(0)).await.unwrap();
    let mut pusher = client.clone();
    let push = tokio::spawn(async move {
        pusher
            .push_transitions(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
    });
    wait_health(&mut client, Duration::from_secs(30), |h| h.env_steps == 4).await;

    let start = Instant::now();
    let status = tokio::task::spawn_blocking(move || {
        let status = learner.sigterm();
        (status, learner)
    })
    .await
    .unwrap();
    let (status, _learner) = status;
    let took = start.elapsed();
    assert!(status.success(), "learner exit: {status:?}");
    assert!(
        took < Duration::from_secs(15),
        "the learner took {took:?} to stop with streams open"
    );
    rfcl_policy::PolicyNet::from_export(&run_dir).expect("the exported policy");

    // Every stream ended: no message after version 1, an end or an error, promptly.
    for mut watch in watchers {
        let next = tokio::time::timeout(Duration::from_secs(5), watch.message())
            .await
            .expect("a WatchPolicy stream still open after the learner stopped");
        assert!(!matches!(next, Ok(Some(_))), "{next:?}");
    }
    let pushed = tokio::time::timeout(Duration::from_secs(5), push)
        .await
        .expect("the PushTransitions call still open after the learner stopped")
        .unwrap();
    drop(tx);
    // The learner either summed the stream up at shutdown or the connection closed under it;
    // what it must not do is keep the caller waiting.
    if let Ok(summary) = pushed {
        assert!(summary.into_inner().accepted <= 4);
    }
}
