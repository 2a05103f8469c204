//! Cross-process tests of the `curriculum-server` binary over real gRPC on loopback: stage 1 to
//! stage 2 with a synthetic outcome model, SIGKILL and a restart continuing exactly from the last
//! snapshot, bad input that gets clear statuses and changes nothing, and calls without the run's
//! token refused.
mod common;

use common::*;
use std::time::Duration;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rfcl_core::demo::DemoSet;
use rfcl_core::lease::{AcquireRequest, ResetLease};
use rfcl_core::run_state::RunState;
use rfcl_curriculum::dashboard::DashboardView;
use rfcl_curriculum::snapshot;
use rfcl_curriculum::state::{DemoResets, ServerState};
use rfcl_proto::v1;

fn acquire_req(actor_id: u32) -> v1::AcquireRequest {
    v1::AcquireRequest {
        actor_id,
        env_index: 0,
        eval: false,
    }
}

fn report_for(lease: &v1::ResetLease, success: bool, ret: f64) -> v1::EpisodeReport {
    v1::EpisodeReport {
        lease_id: lease.lease_id,
        success_at_end: success,
        success_once: success || ret > 0.0,
        episode_return: ret,
        length: lease.time_limit.min(20),
        policy_version: 1,
        stage_epoch: lease.stage_epoch,
        actor_id: 0,
        actor_env_steps: 0,
        policy_env_steps: 0,
        actor_sim_restarts: 0,
        reset_failure: String::new(),
    }
}

/// Success is more likely near the demo's end (easy states) than at its start.
fn synthetic_outcome(
    rng: &mut ChaCha8Rng,
    lease: &v1::ResetLease,
    demo_states: u32,
) -> (bool, f64) {
    if lease.kind == v1::LeaseKind::DemoState as i32 {
        let frac = lease.start_index as f64 / (demo_states - 1) as f64;
        let success = rng.random_bool(0.35 + 0.65 * frac);
        (success, if success { 3.0 } else { 0.0 })
    } else {
        let once = rng.random_bool(0.5);
        (once && rng.random_bool(0.8), if once { 2.0 } else { 0.0 })
    }
}

/// Reports `lease`'s episode; whether the server applied it (a repeat is acknowledged, not applied).
async fn applied(
    client: &mut v1::curriculum_client::CurriculumClient<rfcl_proto::auth::AuthChannel>,
    lease: &v1::ResetLease,
    success: bool,
    ret: f64,
) -> bool {
    client
        .report(report_for(lease, success, ret))
        .await
        .unwrap()
        .into_inner()
        .applied
}

/// A WatchStage stream and its first event: (stage, stage epoch, finished).
async fn watch_stage(
    client: &mut v1::curriculum_client::CurriculumClient<rfcl_proto::auth::AuthChannel>,
) -> (tonic::Streaming<v1::StageEvent>, (u32, u64, bool)) {
    let mut stages = client
        .watch_stage(v1::WatchStageRequest::default())
        .await
        .unwrap()
        .into_inner();
    let first = stages.message().await.unwrap().unwrap();
    (stages, (first.stage, first.stage_epoch, first.finished))
}

/// The run's state as other processes read it (GetState).
async fn state_view(
    client: &mut v1::curriculum_client::CurriculumClient<rfcl_proto::auth::AuthChannel>,
) -> RunState {
    let reply = client.get_state(v1::GetStateRequest {}).await.unwrap();
    rfcl_proto::convert::run_state(reply.get_ref()).unwrap()
}

/// The parts of the view that are curriculum state (not wall-clock dependent).
fn curriculum_part(view: &DashboardView) -> serde_json::Value {
    // A demo's episode id and maze cell come from the demo file, which the running server adds to
    // its view and a snapshot does not hold: they are not curriculum state.
    let v = &view.run;
    let mut demos = v.demos.clone();
    for d in &mut demos {
        d.episode_id = 0;
        d.difficulty.cell = None;
    }
    serde_json::json!({
        "stage": v.stage, "epoch": v.stage_epoch, "env_steps": v.env_steps, "episodes": v.episodes,
        "demos": demos, "levels": view.levels, "stage_1_env_steps": v.stage_1_env_steps,
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stage_1_to_stage_2_then_sigkill_and_resume_continues_from_the_snapshot() {
    let dir = tempfile::tempdir().unwrap();
    let files = RunFiles::write(dir.path(), 30.0);
    let mut server = ServerProcess::start(&files.args("--run-dir", &[]));
    let mut client = server.client().await;

    let initial = state_view(&mut client).await;
    assert_eq!(initial.stage, 1);
    assert_eq!(initial.demos.len(), 3);
    // The dashboard's view embeds the same run state.
    assert_eq!(server.view().run, initial);
    // S_i = 21 states (no truncation: 5 success steps), t_i starts at S_i - 1.
    assert!(initial
        .demos
        .iter()
        .all(|d| d.states == 21 && d.t == 20 && !d.solved));

    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut stage_2_reports = 0;
    let mut reports = 0;
    while stage_2_reports < 37 {
        reports += 1;
        assert!(
            reports < 20_000,
            "stage 1 did not end within 20000 episodes"
        );
        let lease = client.acquire(acquire_req(0)).await.unwrap().into_inner();
        if lease.kind == v1::LeaseKind::DemoState as i32 {
            assert_eq!(
                lease.env_state,
                vec![lease.demo_id as f32, lease.start_index as f32, 0.5, -0.5]
            );
            assert_eq!(
                lease.reset.as_ref().unwrap().seed,
                100 + lease.demo_id as u64
            );
            assert!(lease.time_limit >= 16 && lease.time_limit <= 100);
        } else {
            stage_2_reports += 1;
            assert_eq!(lease.stage, 2);
            assert_eq!(
                lease.time_limit, 100,
                "stage-2 episodes run the env horizon"
            );
        }
        let (success, ret) = synthetic_outcome(&mut rng, &lease, 21);
        assert!(applied(&mut client, &lease, success, ret).await);
    }
    let before_kill = state_view(&mut client).await;
    assert_eq!(before_kill.stage, 2);
    assert_eq!(before_kill.stage_epoch, 1);
    assert!(before_kill.demos.iter().all(|d| d.solved && d.t == 0));
    assert!(before_kill.stage_1_env_steps.unwrap() > 0);
    assert_eq!(
        server.view().levels.len(),
        10 + 3,
        "10 seeds + 3 demo starts (deviation 3)"
    );

    // Kill -9: no final snapshot. The last periodic snapshot is what a restart must continue from.
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    server.sigkill();
    let snap_path = snapshot::snapshot_path(&files.run_dir);
    let mut snap = snapshot::load(&snap_path, "ctest").expect("a periodic snapshot exists");
    assert!(snap.stats.episodes > 0 && snap.stats.episodes <= before_kill.episodes);

    // Started as before, it finds its snapshot in its run directory and continues from it.
    let mut restarted = ServerProcess::start(&files.args("--run-dir", &[]));
    let mut client = restarted.client().await;
    let resumed = restarted.view();
    let snap_view = snap.view(
        "ctest",
        "PointMaze-v0",
        rfcl_curriculum::state::unix_now(),
        50_000,
    );
    assert_eq!(curriculum_part(&resumed), curriculum_part(&snap_view));

    // The restarted server hands out exactly what the snapshot's state hands out in-process.
    let cfg = rfcl_core::config::resolve_file(&files.config, &[]).unwrap();
    let set = {
        let _guard = rfcl_testkit::hdf5::fork_guard();
        DemoSet::load(&files.demos)
            .unwrap()
            .select(3, false, 7)
            .unwrap()
    };
    let resets = DemoResets::from_demos(&set);
    for _ in 0..25 {
        let expected: ResetLease = snap
            .acquire(
                AcquireRequest {
                    actor_id: 0,
                    env_index: 0,
                    eval: false,
                },
                &cfg,
                &resets,
                0.0,
            )
            .unwrap();
        let got = ResetLease::try_from(client.acquire(acquire_req(0)).await.unwrap().into_inner())
            .unwrap();
        assert_eq!(got, expected);
    }
    // A clean stop writes a final snapshot and exits 0.
    assert!(restarted.sigterm().success());
    let last = snapshot::load(&snap_path, "ctest").unwrap();
    assert_eq!(last.leases.granted_total(), snap.leases.granted_total());
    let _: &ServerState = &last;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_reports_get_clear_statuses_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start_fresh(dir.path(), 30.0);
    let mut client = server.client().await;
    let lease = client.acquire(acquire_req(0)).await.unwrap().into_inner();
    let before = curriculum_part(&server.view());

    type Spoil = fn(&mut v1::EpisodeReport);
    let refused: [(Spoil, tonic::Code, &[&str]); 4] = [
        (
            |r| r.lease_id = 0,
            tonic::Code::InvalidArgument,
            &["EpisodeReport.lease_id"],
        ),
        (
            |r| r.episode_return = f64::NAN,
            tonic::Code::InvalidArgument,
            &["episode_return"],
        ),
        (
            |r| r.lease_id = 999_999,
            tonic::Code::NotFound,
            &["lease 999999 is unknown"],
        ),
        (
            |r| r.stage_epoch = 5,
            tonic::Code::FailedPrecondition,
            &["stage epoch 0", "says 5"],
        ),
    ];
    for (spoil, code, says) in refused {
        let mut report = report_for(&lease, true, 1.0);
        spoil(&mut report);
        let status = client.report(report).await.unwrap_err();
        assert_eq!(status.code(), code, "{}", status.message());
        assert!(
            says.iter().all(|s| status.message().contains(s)),
            "{}",
            status.message()
        );
    }

    assert_eq!(
        curriculum_part(&server.view()),
        before,
        "refused reports changed the curriculum"
    );

    // The real report applies once; its repeat is acknowledged and changes nothing.
    assert!(applied(&mut client, &lease, true, 1.0).await);
    let after_one = curriculum_part(&server.view());
    assert_ne!(after_one, before);
    assert!(!applied(&mut client, &lease, true, 1.0).await);
    assert_eq!(curriculum_part(&server.view()), after_one);

    // ReportAndAcquire: the report applies once and the next lease comes back in the same reply.
    let lease2 = client.acquire(acquire_req(0)).await.unwrap().into_inner();
    let both = v1::ReportAndAcquireRequest {
        report: Some(report_for(&lease2, false, 0.0)),
        next: Some(acquire_req(0)),
    };
    let reply = client
        .report_and_acquire(both.clone())
        .await
        .unwrap()
        .into_inner();
    assert!(reply.ack.unwrap().applied);
    let lease3 = reply.lease.expect("the next lease");
    assert!(lease3.lease_id > lease2.lease_id);
    // Repeated: acknowledged, not applied, and still a fresh lease.
    let reply = client.report_and_acquire(both).await.unwrap().into_inner();
    assert!(!reply.ack.unwrap().applied);
    assert!(reply.lease.unwrap().lease_id > lease3.lease_id);
    // Refused: the call fails with Report's status and hands out no lease.
    let mut unknown = report_for(&lease3, true, 1.0);
    unknown.lease_id = 888_888;
    let open_before = server.view().open_leases;
    let refused = v1::ReportAndAcquireRequest {
        report: Some(unknown),
        next: Some(acquire_req(0)),
    };
    let status = client.report_and_acquire(refused).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::NotFound);
    assert_eq!(server.view().open_leases, open_before);
    let empty = v1::ReportAndAcquireRequest {
        report: None,
        next: None,
    };
    let status = client.report_and_acquire(empty).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);

    let view = server.view();
    let r = view.run.refused_reports;
    assert_eq!(
        (r.malformed, r.unknown, r.epoch_mismatch, r.duplicate),
        (3, 2, 1, 2)
    );
    assert_eq!(state_view(&mut client).await.refused_reports, r);
    assert_eq!(
        view.actors.len(),
        1,
        "the actor is listed with its last-seen time"
    );
    assert_eq!((view.actors[0].actor_id, view.actors[0].episodes), (0, 2));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unreported_leases_expire_and_are_counted() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start_fresh(dir.path(), 0.3);
    let mut client = server.client().await;
    let lease = client.acquire(acquire_req(1)).await.unwrap().into_inner();
    let before = curriculum_part(&server.view());
    let mut view = state_view(&mut client).await;
    for _ in 0..50 {
        if view.expired_leases == 1 {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
        view = state_view(&mut client).await;
    }
    assert_eq!(view.expired_leases, 1);
    assert_eq!(server.view().open_leases, 0);
    let status = client
        .report(report_for(&lease, true, 1.0))
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::FailedPrecondition);
    assert!(status.message().contains("expired"), "{}", status.message());
    assert_eq!(curriculum_part(&server.view()), before);
}

#[test]
fn startup_errors_are_one_clear_line() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path(), 30.0);
    let missing = dir.path().join("nope.h5");
    let out = run_server(
        &[
            "--demos",
            missing.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
        ],
        Some(TEST_TOKEN),
    );
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    let line = stderr
        .lines()
        .find(|l| l.starts_with("error:"))
        .expect("an error line");
    assert!(line.contains("nope.h5"), "{line}");

    // A file that crashes libhdf5 itself is named, not a segmentation fault.
    let damaged = rfcl_testkit::demos::hdf5_crash_reproducer(dir.path());
    let out = run_server(
        &[
            "--demos",
            damaged.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
        ],
        Some(TEST_TOKEN),
    );
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    let errors: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(errors.len(), 1, "{stderr}");
    assert!(
        errors[0].contains("damaged.h5") && errors[0].contains("crashed the HDF5 library"),
        "{}",
        errors[0]
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn calls_without_the_run_token_are_refused_counted_and_change_nothing() {
    use rfcl_proto::auth::{authenticated, Token};
    use rfcl_proto::v1::curriculum_client::CurriculumClient;
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start_fresh(dir.path(), 30.0);
    let mut client = server.client().await;
    let lease = client.acquire(acquire_req(0)).await.unwrap().into_inner();
    let before = curriculum_part(&server.view());

    let mut bare = CurriculumClient::new(server.channel().await);
    let wrong = Token::parse("not-the-run-token-0123", "a test").unwrap();
    let mut forged = CurriculumClient::new(authenticated(server.channel().await, &wrong));
    for status in [
        bare.acquire(acquire_req(1)).await.unwrap_err(),
        bare.report(report_for(&lease, true, 1.0))
            .await
            .unwrap_err(),
        forged
            .report(report_for(&lease, true, 1.0))
            .await
            .unwrap_err(),
        forged.get_state(v1::GetStateRequest {}).await.unwrap_err(),
        forged
            .watch_stage(v1::WatchStageRequest::default())
            .await
            .unwrap_err(),
    ] {
        assert_eq!(status.code(), tonic::Code::Unauthenticated, "{status:?}");
        assert!(
            status.message().contains("RFCL_TOKEN"),
            "{}",
            status.message()
        );
    }
    let after = server.view();
    assert_eq!(
        curriculum_part(&after),
        before,
        "refused calls changed nothing"
    );
    assert_eq!(
        after.open_leases, 1,
        "the forged report did not close the lease"
    );
    assert_eq!(after.unauthenticated_calls, 5);
    let metrics = server.dashboard_get("metrics");
    assert!(
        metrics.contains("rfcl_curriculum_unauthenticated_calls_total 5"),
        "{metrics}"
    );
    // The standard health service answers without a token: probes cannot send one.
    let endpoint = tonic::transport::Endpoint::from_shared(server.grpc.clone()).unwrap();
    let serving = rfcl_proto::health::check(
        endpoint,
        "rfcl.v1.Curriculum",
        std::time::Duration::from_secs(5),
    )
    .await
    .unwrap();
    assert!(serving);
    // The reported lease is still the holder's to report.
    assert!(applied(&mut client, &lease, true, 1.0).await);
}

#[test]
fn a_server_without_a_run_token_does_not_start() {
    let dir = tempfile::tempdir().unwrap();
    let demos = write_demos(dir.path(), 1, 20);
    let config = write_config(dir.path(), 30.0);
    let out = run_server(
        &[
            "--demos",
            demos.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
        ],
        None,
    );
    assert!(!out.status.success());
    assert!(out.stdout.is_empty(), "no ready line");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("no run token") && stderr.contains("RFCL_TOKEN_FILE"),
        "{stderr}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_a_certificate_the_server_speaks_tls_only() {
    use rfcl_proto::auth::{ClientAuth, TLS_CERT_ENV, TLS_KEY_ENV};
    use rfcl_proto::v1::curriculum_client::CurriculumClient;
    let dir = tempfile::tempdir().unwrap();
    let cert = rcgen::generate_simple_self_signed(vec!["localhost".to_string()]).unwrap();
    let (cert_path, key_path) = (dir.path().join("cert.pem"), dir.path().join("key.pem"));
    std::fs::write(&cert_path, cert.cert.pem()).unwrap();
    std::fs::write(&key_path, cert.signing_key.serialize_pem()).unwrap();
    let demos = write_demos(dir.path(), 3, 20);
    let config = write_config(dir.path(), 30.0);
    let run_dir = dir.path().join("run");
    let server = ServerProcess::start_with_env(
        &[
            "--demos",
            demos.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
            "--run-dir",
            run_dir.to_str().unwrap(),
        ],
        &[(TLS_CERT_ENV, &cert_path), (TLS_KEY_ENV, &key_path)],
    );
    let port = server.grpc.rsplit(':').next().unwrap();
    let url = format!("https://localhost:{port}");

    // A client that trusts the certificate and carries the token gets through.
    let auth = ClientAuth::plain(test_token())
        .with_tls_ca(&cert_path)
        .unwrap();
    let endpoint = auth
        .endpoint(tonic::transport::Endpoint::from_shared(url.clone()).unwrap())
        .unwrap();
    let mut client = CurriculumClient::new(auth.wrap(endpoint.connect().await.unwrap()));
    let view = state_view(&mut client).await;
    assert_eq!(view.demos.len(), 3);

    // A plain-text client gets nowhere.
    let plain = tonic::transport::Endpoint::from_shared(format!("http://localhost:{port}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut plain = CurriculumClient::new(authenticated_test(plain));
    assert!(plain.get_state(v1::GetStateRequest {}).await.is_err());
}

fn authenticated_test(channel: tonic::transport::Channel) -> rfcl_proto::auth::AuthChannel {
    rfcl_proto::auth::authenticated(channel, &test_token())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_run_finishes_when_the_last_five_evals_reach_the_bar() {
    let dir = tempfile::tempdir().unwrap();
    let demos = write_demos(dir.path(), 3, 20);
    let config = write_config(dir.path(), 30.0);
    let run_dir = dir.path().join("run");
    // 1 eval env × 100 steps / horizon 100 = 1 episode, raised to 10 per evaluation.
    let server = ServerProcess::start(&[
        "--demos",
        demos.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--run-dir",
        run_dir.to_str().unwrap(),
        "service.stop_at_eval_success=0.85",
        "eval_env.num_envs=1",
        "sac.eval_steps=100",
    ]);
    let mut client = server.client().await;
    let (mut stages, first) = watch_stage(&mut client).await;
    assert_eq!(first, (1, 0, false));

    let eval_req = v1::AcquireRequest {
        actor_id: 9,
        env_index: 0,
        eval: true,
    };
    // Evals of versions 1..=5 at 1k..5k env steps: 8, 10, 9, 8, 9 of 10 successes. The running
    // mean of the five is 0.88 >= 0.85, reached with the fiftieth episode and not before.
    let successes = [8, 10, 9, 8, 9];
    for (v, wins) in successes.into_iter().enumerate() {
        let version = v as u64 + 1;
        for episode in 0..10 {
            let lease = client.acquire(eval_req).await.unwrap().into_inner();
            let report = v1::EpisodeReport {
                success_at_end: episode < wins,
                success_once: episode < wins,
                policy_version: version,
                policy_env_steps: 1000 * version,
                actor_id: 9,
                ..report_for(&lease, false, 0.0)
            };
            let ack = client.report(report).await.unwrap().into_inner();
            let last = version == 5 && episode == 9;
            assert_eq!(
                ack.stage_epoch,
                u64::from(last),
                "version {version} episode {episode}"
            );
        }
    }
    let end = stages.message().await.unwrap().unwrap();
    assert_eq!((end.stage, end.stage_epoch, end.finished), (1, 1, true));
    let view = state_view(&mut client).await;
    assert!(view.finished);
    // Nothing more is handed out, to train or eval actors.
    for req in [acquire_req(0), eval_req] {
        let status = client.acquire(req).await.unwrap_err();
        assert_eq!(status.code(), tonic::Code::FailedPrecondition);
        assert!(
            status.message().contains("stop_at_eval_success"),
            "{}",
            status.message()
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_with_open_stage_watches_exits_promptly_and_writes_the_snapshot() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = ServerProcess::start_fresh(dir.path(), 30.0);
    let mut client = server.client().await;
    // Two learners watching the stage on their own connections; their streams never end by
    // themselves.
    let mut watches = Vec::new();
    for _ in 0..2 {
        let mut c = server.client().await;
        let (stream, (stage, _, _)) = watch_stage(&mut c).await;
        assert_eq!(stage, 1);
        watches.push((c, stream));
    }
    let lease = client.acquire(acquire_req(0)).await.unwrap().into_inner();
    client.report(report_for(&lease, true, 1.0)).await.unwrap();
    assert_eq!(state_view(&mut client).await.episodes, 1);

    server.child.signal(rfcl_testkit::child::Signal::TERM);
    let t0 = std::time::Instant::now();
    let status = loop {
        if let Some(status) = server.child.try_wait().unwrap() {
            break status;
        }
        assert!(
            t0.elapsed() < std::time::Duration::from_secs(5),
            "still running 5 s after SIGTERM with two stage watches open"
        );
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    };
    assert!(status.success(), "{status}");
    // The watches were ended by the server (status OK), not cut off.
    for (_, mut stream) in watches {
        let end = tokio::time::timeout(std::time::Duration::from_secs(2), stream.message())
            .await
            .expect("the stage watch did not end");
        assert!(matches!(end, Ok(None)), "{end:?}");
    }
    let snap = snapshot::load(&snapshot::snapshot_path(&dir.path().join("run")), "ctest")
        .expect("the final snapshot");
    assert_eq!(snap.stats.episodes, 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reports_beyond_their_lease_are_refused_counted_and_leave_it_open() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start_fresh(dir.path(), 30.0);
    let mut client = server.client().await;
    let lease = client.acquire(acquire_req(0)).await.unwrap().into_inner();
    let before = curriculum_part(&server.view());

    let too_long = v1::EpisodeReport {
        length: u32::MAX,
        ..report_for(&lease, true, 1.0)
    };
    let status = client.report(too_long.clone()).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    let bound = format!("at most {}", lease.time_limit);
    assert!(
        status.message().contains("EpisodeReport.length") && status.message().contains(&bound),
        "{}",
        status.message()
    );
    // The same through ReportAndAcquire: refused, and no lease handed out.
    let status = client
        .report_and_acquire(v1::ReportAndAcquireRequest {
            report: Some(v1::EpisodeReport {
                length: lease.time_limit + 1,
                ..too_long
            }),
            next: Some(acquire_req(0)),
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    let stranger = v1::EpisodeReport {
        actor_id: 7,
        ..report_for(&lease, true, 1.0)
    };
    let status = client.report(stranger).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::PermissionDenied);
    assert!(
        status.message().contains("EpisodeReport.actor_id")
            && status.message().contains("held by actor 0"),
        "{}",
        status.message()
    );

    let view = server.view();
    assert_eq!(
        curriculum_part(&view),
        before,
        "refused reports changed the curriculum"
    );
    assert_eq!(view.run.env_steps, 0);
    assert_eq!(
        (
            view.run.refused_reports.over_time_limit,
            view.run.refused_reports.not_holder
        ),
        (2, 1)
    );
    assert_eq!(view.open_leases, 1, "the lease stays open for its holder");
    let metrics = server.dashboard_get("metrics");
    for line in [
        "rfcl_curriculum_reports_refused_total{reason=\"over_time_limit\"} 2",
        "rfcl_curriculum_reports_refused_total{reason=\"not_holder\"} 1",
    ] {
        assert!(metrics.contains(line), "{line} missing from {metrics}");
    }
    // Its holder's report still applies, with the steps it claims.
    assert!(applied(&mut client, &lease, true, 1.0).await);
    assert_eq!(
        state_view(&mut client).await.env_steps,
        u64::from(lease.time_limit.min(20))
    );
}

/// Posts one gRPC frame that declares a message of `declared_len` bytes to `method` with curl
/// (the generated clients cannot send more than their message holds); returns the response
/// headers and trailers. At most 64 bytes of the message are sent: the server must refuse on the
/// declared length, before reading the body (and curl gives up on a stream that the server resets
/// while the body is still being sent).
fn raw_grpc_call(server: &ServerProcess, method: &str, declared_len: usize) -> String {
    let dir = tempfile::tempdir().unwrap();
    let body = dir.path().join("body");
    let mut frame = vec![0u8];
    frame.extend_from_slice(&(declared_len as u32).to_be_bytes());
    frame.resize(5 + declared_len.min(64), 0);
    std::fs::write(&body, frame).unwrap();
    let out = std::process::Command::new("curl")
        .args([
            "-sS",
            "--http2-prior-knowledge",
            "-X",
            "POST",
            "-H",
            "content-type: application/grpc",
            "-H",
            "te: trailers",
            "-H",
            &format!("authorization: Bearer {TEST_TOKEN}"),
            "--data-binary",
            &format!("@{}", body.display()),
            "-D",
            "-",
            "-o",
            "/dev/null",
            &format!("{}/rfcl.v1.Curriculum/{method}", server.grpc),
        ])
        .output()
        .unwrap();
    format!(
        "{}\n(curl: {}; {})",
        String::from_utf8_lossy(&out.stdout),
        out.status,
        String::from_utf8_lossy(&out.stderr)
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_oversized_request_is_refused_and_the_server_keeps_serving() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start_fresh(dir.path(), 30.0);
    // The frame check itself: an empty GetState request gets through it.
    let small = raw_grpc_call(&server, "GetState", 0);
    assert!(small.contains("grpc-status: 0"), "{small}");
    // 1 MiB is far beyond any request of this service (a few dozen bytes): refused on its
    // declared length, OUT_OF_RANGE (tonic's code for a message over the limit) naming the limit.
    let big = raw_grpc_call(&server, "ReportAndAcquire", 1 << 20);
    assert!(big.contains("grpc-status: 11"), "{big}");
    // grpc-message is percent-encoded.
    assert!(big.contains("limit%20is:%2065536%20bytes"), "{big}");
    // And the server goes on serving.
    let mut client = server.client().await;
    let lease = client.acquire(acquire_req(0)).await.unwrap().into_inner();
    assert!(applied(&mut client, &lease, true, 1.0).await);
    assert_eq!(state_view(&mut client).await.episodes, 1);
    // Refused before any handler ran, and still counted and shown.
    assert_eq!(
        server.view().oversized_requests,
        1,
        "the small call is not counted"
    );
    let metrics = server.dashboard_get("metrics");
    assert!(
        metrics.contains("rfcl_curriculum_oversized_requests_total 1"),
        "{metrics}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stage_1_only_run_resumed_without_it_goes_on_into_stage_2() {
    let dir = tempfile::tempdir().unwrap();
    let files = RunFiles::write(dir.path(), 30.0);
    let mut server = ServerProcess::start(&files.args("--run-dir", &["train.stage_1_only=true"]));
    let mut client = server.client().await;
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut reports = 0;
    loop {
        let lease = match client.acquire(acquire_req(0)).await {
            Ok(lease) => lease.into_inner(),
            Err(status) if status.code() == tonic::Code::FailedPrecondition => break,
            Err(status) => panic!("{status}"),
        };
        assert_eq!(lease.kind, v1::LeaseKind::DemoState as i32);
        let (success, ret) = synthetic_outcome(&mut rng, &lease, 21);
        client
            .report(report_for(&lease, success, ret))
            .await
            .unwrap();
        reports += 1;
        assert!(
            reports < 20_000,
            "stage 1 did not end within 20000 episodes"
        );
    }
    let ended = state_view(&mut client).await;
    assert!(ended.finished && ended.stage == 1, "{ended:?}");
    let stage_1_end = ended.stage_1_env_steps.expect("stage 1 ended");
    assert!(server.sigterm().success());

    // Resumed under the config without stage_1_only: stage 2 in a new epoch, stage 1's end kept.
    let restarted = ServerProcess::start(&files.args("--resume", &[]));
    let mut client = restarted.client().await;
    let (_stages, first) = watch_stage(&mut client).await;
    assert_eq!(first, (2, 2, false));
    let view = state_view(&mut client).await;
    assert_eq!(view.stage_1_env_steps, Some(stage_1_end));
    assert_eq!(view.env_steps, ended.env_steps);
    let lease = client.acquire(acquire_req(0)).await.unwrap().into_inner();
    assert_eq!((lease.kind, lease.stage), (v1::LeaseKind::Level as i32, 2));
    assert!(applied(&mut client, &lease, true, 2.0).await);
}

/// Stops a run in stage 1, resumes it with `change` and asserts that the server refuses, naming
/// the run directory and each of `expected`.
async fn a_stage_1_run_refuses_to_resume_with(change: &str, expected: &[&str]) {
    let dir = tempfile::tempdir().unwrap();
    let files = RunFiles::write(dir.path(), 30.0);
    let mut server = ServerProcess::start(&files.args("--run-dir", &[]));
    assert_eq!(state_view(&mut server.client().await).await.stage, 1);
    assert!(server.sigterm().success());
    let out = run_server(&files.args("--resume", &[change]), Some(TEST_TOKEN));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains(files.run_dir.to_str().unwrap())
            && expected.iter().all(|part| stderr.contains(part)),
        "{stderr}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_in_stage_1_cannot_be_resumed_forward_only() {
    a_stage_1_run_refuses_to_resume_with(
        "train.stage_2_only=true",
        &["still in stage 1", "train.stage_2_only"],
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_in_stage_1_refuses_changed_reverse_options_on_resume() {
    a_stage_1_run_refuses_to_resume_with(
        "reverse.reverse_step_size=8",
        &["reverse.reverse_step_size: 4 -> 8", "stage 1"],
    )
    .await;
}

/// Whatever the dashboard's clients do, training goes on: with the server at 1,024 open files,
/// 2,000 idle connections to its dashboard (anyone who can reach the port can open them, no token
/// needed) leave the gRPC service answering with the run's token; the dashboard keeps at most
/// its bound of them open, closes the rest at once and counts them, and serves again as soon as
/// they go.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_idle_dashboard_connections_cannot_starve_training() {
    use rfcl_curriculum::dashboard_listener::MAX_CONNECTIONS;
    const FLOOD: usize = 2000;
    // This test holds the flood's sockets itself: its own limit must allow them.
    let raised = std::process::Command::new("prlimit")
        .args(["--pid", &std::process::id().to_string(), "--nofile=8192:"])
        .status()
        .unwrap();
    assert!(
        raised.success(),
        "prlimit could not raise this test's open-file limit"
    );
    let dir = tempfile::tempdir().unwrap();
    let files = RunFiles::write(dir.path(), 30.0);
    let server = ServerProcess::start_with_file_limit(&files.args("--run-dir", &[]), 1024);
    let addr = server
        .dashboard
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_string();
    let flood: Vec<std::net::TcpStream> = (0..FLOOD)
        .map(|i| {
            std::net::TcpStream::connect(&addr)
                .unwrap_or_else(|e| panic!("connection {i} to the dashboard: {e}"))
        })
        .collect();
    // Training's calls go through.
    let mut client = server.client().await;
    let lease = tokio::time::timeout(Duration::from_secs(10), client.acquire(acquire_req(0)))
        .await
        .expect("Acquire answered within 10 s")
        .unwrap()
        .into_inner();
    assert!(applied(&mut client, &lease, true, 1.0).await);
    // Once the flood goes, the dashboard serves again, and /metrics shows how many connections
    // it closed at once to keep its bound.
    drop(flood);
    let mut metrics = String::new();
    for _ in 0..50 {
        let out = std::process::Command::new("curl")
            .args(["-sf", "-m", "2", &format!("{}metrics", server.dashboard)])
            .output()
            .unwrap();
        if out.status.success() {
            metrics = String::from_utf8(out.stdout).unwrap();
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let refused: usize = metrics
        .lines()
        .find_map(|l| l.strip_prefix("rfcl_curriculum_dashboard_connections_refused_total "))
        .unwrap_or_else(|| panic!("no refused-connections count in {metrics}"))
        .trim()
        .parse()
        .unwrap();
    assert!(
        refused + MAX_CONNECTIONS >= FLOOD && refused < FLOOD,
        "{refused} of {FLOOD} refused with a bound of {MAX_CONNECTIONS}"
    );
}
