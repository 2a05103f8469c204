//! The learner binary over real gRPC on loopback, with a real curriculum server: the run
//! description, transitions in, the spec 5.2/5.4 schedule under the `sync` limiter, whole policy
//! versions out, and malformed batches refused with INVALID_ARGUMENT.
mod service_support;

use std::time::Duration;

use rfcl_policy::PolicyNet;
use rfcl_proto::v1;
use service_support::*;

/// Warm-up of these tests: the first iteration is earned at 12 env steps (pre-increment 8 >= 8).
const W: u64 = 8;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn run_info_updates_on_schedule_and_whole_policy_versions() {
    let dir = tempfile::tempdir().unwrap();
    let pair = start_pair(dir.path(), W, 100_000, "", &[]);
    let mut client = pair.learner.client().await;

    let info = client
        .get_run_info(v1::GetRunInfoRequest {
            actor_id: 1,
            hostname: "test".into(),
            host_identity: "machine-id=another-host".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!((info.obs_dim, info.action_dim), (OBS as u32, ACT as u32));
    assert_eq!(info.env_id, "PointMaze-v0");
    assert_eq!(info.run_name, "ltest");
    // Not on the learner's host: gRPC (service_shm.rs covers the same-host case).
    assert_eq!(info.transport, "grpc");
    assert_eq!(info.curriculum_addr, pair.curriculum.grpc);
    assert_eq!(info.run_seed, 3);
    assert_eq!(info.policy_version, 1);
    // No train.data_action_scale: no scale (spec 6.4; service_export.rs has one).
    assert!(info.action_scale.is_empty());
    assert!(!info.learner_hostname.is_empty());
    let cfg = rfcl_core::config::resolve_file(&pair.config, &[]).unwrap();
    assert_eq!(info.config_yaml, rfcl_core::config::to_yaml(&cfg));

    // An actor with no policy asks for versions after 0 and gets the initial one at once.
    let mut watch = client
        .watch_policy(v1::WatchPolicyRequest { after_version: 0 })
        .await
        .unwrap()
        .into_inner();
    let first = watch.message().await.unwrap().unwrap();
    assert_eq!((first.version, first.learner_env_steps), (1, 0));
    let initial = PolicyNet::from_safetensors(&first.safetensors, &cfg, OBS, ACT).unwrap();

    // 40 env steps: the reference runs its iterations after 12, 16, ..., 40 steps: 8 of them.
    let summary = push(&mut client, batches(0..40, 6, 0)).await.unwrap();
    assert_eq!((summary.accepted, summary.dropped_stale_epoch), (40, 0));
    assert_eq!(earned(40, W), 8);
    let h = wait_health(&mut client, Duration::from_secs(60), |h| {
        h.policy_version == 9
    })
    .await;
    assert_eq!((h.env_steps, h.updates), (40, G * 8));
    assert!(h.ok);

    // Every version that arrives is whole (it loads) and carries the env steps it was made at:
    // version v follows v - 1 iterations, the (v-1)-th earned at (W/K + v - 1)·K steps.
    let mut last = first.version;
    let mut obs = vec![0.0f32; OBS];
    obs[0] = 0.3;
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
    let before = initial.act(&obs, true, &mut rng);
    while last < 9 {
        let weights = tokio::time::timeout(Duration::from_secs(30), watch.message())
            .await
            .expect("a newer policy version")
            .unwrap()
            .unwrap();
        assert!(weights.version > last, "versions only grow");
        assert_eq!(weights.learner_env_steps, (W / K + weights.version - 1) * K);
        initial.load(&weights.safetensors).unwrap();
        last = weights.version;
    }
    assert_ne!(
        initial.act(&obs, true, &mut rng),
        before,
        "training moved the policy"
    );

    // A late watcher that already has version 9 gets nothing until version 10.
    let mut late = client
        .watch_policy(v1::WatchPolicyRequest { after_version: 9 })
        .await
        .unwrap()
        .into_inner();
    assert!(
        tokio::time::timeout(Duration::from_millis(300), late.message())
            .await
            .is_err(),
        "nothing newer than 9 yet"
    );
    push(&mut client, batches(40..44, 4, 0)).await.unwrap();
    let v10 = tokio::time::timeout(Duration::from_secs(30), late.message())
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert_eq!((v10.version, v10.learner_env_steps), (10, 44));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sync_mode_never_lets_data_run_ahead_of_the_updates() {
    let dir = tempfile::tempdir().unwrap();
    let pair = start_sync_pair(dir.path(), W);
    let learner = &pair.learner;
    let mut pusher = learner.client().await;
    let mut watcher = learner.client().await;

    const N: u64 = 600;
    let push = tokio::spawn(async move { push(&mut pusher, batches(0..N, 8, 0)).await });
    let mut samples = 0;
    loop {
        let h = health(&mut watcher).await;
        let iterations = h.updates / G;
        let owed = earned(h.env_steps, W);
        // The ingest stops at each iteration boundary until that iteration ran.
        assert!(
            iterations == owed || iterations + 1 == owed,
            "{iterations} iterations at {} env steps, the schedule owes {owed}",
            h.env_steps
        );
        samples += 1;
        if h.env_steps == N && iterations == owed {
            break;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    assert!(samples > 5);
    let summary = push.await.unwrap().unwrap();
    assert_eq!(summary.accepted, N);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_batches_get_invalid_argument_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let pair = start_pair(dir.path(), W, 100_000, "", &[]);
    let learner = &pair.learner;
    let mut client = learner.client().await;

    let good = batches(0..3, 3, 0).remove(0);
    let mut wrong_obs = good.clone();
    wrong_obs.obs_dim = 5;
    let mut wrong_action = good.clone();
    wrong_action.action_dim = 3;
    let mut short = good.clone();
    short.records.truncate(good.records.len() - 8);
    let mut wrong_count = good.clone();
    wrong_count.count = 4;
    let mut nan = good.clone();
    // obs[1] of record 2 (obs starts after the 32-byte header).
    let record_bytes = good.records.len() / 3;
    let at = 2 * record_bytes + 32 + 4;
    nan.records[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());

    for (batch, expected) in [
        (wrong_obs, "TransitionBatch.obs_dim"),
        (wrong_action, "TransitionBatch.action_dim"),
        (short, "TransitionBatch.records"),
        (wrong_count, "TransitionBatch.records"),
        (nan, "record 2: obs[1] is NaN"),
    ] {
        // The malformed batch comes after a good one in the same stream.
        let status = push(&mut client, vec![good.clone(), batch])
            .await
            .expect_err("a malformed batch is refused");
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
        assert!(
            status.message().contains(expected),
            "{:?} should name {expected}",
            status.message()
        );
    }
    // The good batches before them were taken; the learner is healthy and takes more.
    let summary = push(&mut client, vec![good.clone()]).await.unwrap();
    assert_eq!(summary.accepted, 3);
    let h = wait_health(&mut client, Duration::from_secs(30), |h| h.env_steps == 18).await;
    assert!(h.ok);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn async_mode_updates_flat_out_and_reports_the_achieved_ratio() {
    let dir = tempfile::tempdir().unwrap();
    let run_dir = dir.path().join("run");
    let demos = write_demos(dir.path());
    let config = write_config(dir.path(), W, 100_000, "  utd_mode: async\n");
    let curriculum = Curriculum::start(&config, &demos, &run_dir);
    let args = Learner::args(&config, &curriculum.grpc, &demos, &run_dir);
    let args: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    let mut learner = Learner::start(&args);
    let mut client = learner.client().await;

    // Past the warm-up (12 steps), the learner keeps updating without new data.
    push(&mut client, batches(0..16, 8, 0)).await.unwrap();
    let h = wait_health(&mut client, Duration::from_secs(60), |h| {
        h.updates >= G * 10 * earned(16, W)
    })
    .await;
    assert_eq!(h.env_steps, 16);
    assert!(learner.sigterm().success());

    let csv = std::fs::read_to_string(run_dir.join("metrics.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let last: Vec<&str> = csv.lines().last().unwrap().split(',').collect();
    let value = |name: &str| -> f64 {
        last[header.iter().position(|h| *h == name).unwrap()]
            .parse()
            .unwrap()
    };
    assert_eq!(value("learner/utd_target"), G as f64 / K as f64);
    assert!(
        value("learner/utd") >= 10.0 * value("learner/utd_target"),
        "achieved UTD {} is reported",
        value("learner/utd")
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn calls_without_the_run_token_are_refused_counted_and_change_nothing() {
    use rfcl_proto::auth::{authenticated, Token};
    use rfcl_proto::v1::learner_client::LearnerClient;
    let dir = tempfile::tempdir().unwrap();
    let pair = start_pair(dir.path(), W, 100_000, "", &[]);
    let learner = &pair.learner;
    let channel = || async {
        tonic::transport::Channel::from_shared(learner.grpc.clone())
            .unwrap()
            .connect()
            .await
            .unwrap()
    };
    let wrong = Token::parse("not-the-run-token-0123", "a test").unwrap();
    let mut forged = LearnerClient::new(authenticated(channel().await, &wrong));
    let mut bare = LearnerClient::new(channel().await);
    let refusals = [
        push(&mut forged, batches(0..40, 6, 0)).await.unwrap_err(),
        bare.health(v1::HealthRequest {}).await.unwrap_err(),
        forged
            .watch_policy(v1::WatchPolicyRequest { after_version: 0 })
            .await
            .unwrap_err(),
        forged
            .get_run_info(v1::GetRunInfoRequest::default())
            .await
            .unwrap_err(),
    ];
    for status in refusals {
        assert_eq!(status.code(), tonic::Code::Unauthenticated, "{status:?}");
    }
    let mut client = learner.client().await;
    let h = health(&mut client).await;
    assert_eq!(h.env_steps, 0, "the forged transitions were not taken");
    assert_eq!(h.grpc_records, 0);
    assert_eq!(h.unauthenticated_calls, 4);
    // The standard health service needs no token (container probes send none).
    let endpoint = tonic::transport::Endpoint::from_shared(learner.grpc.clone()).unwrap();
    assert!(
        rfcl_proto::health::check(endpoint, "rfcl.v1.Learner", Duration::from_secs(5))
            .await
            .unwrap()
    );
}
