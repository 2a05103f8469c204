//! The dashboard in a real browser: headless Chromium (Debian's `chromium`) loads the page served
//! by the `curriculum-server` binary and must render one bar per demo, the SVG charts, and the
//! JSON and metrics endpoints must agree with it.
mod common;

use common::*;
use rfcl_testkit::browser::{dump_dom, headless};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn chromium_renders_the_demo_bars() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start_fresh(dir.path(), 30.0);
    // Some progress so the page has something to show.
    let mut client = server.client().await;
    for _ in 0..30 {
        let lease = client
            .acquire(rfcl_proto::v1::AcquireRequest {
                actor_id: 2,
                env_index: 0,
                eval: false,
            })
            .await
            .unwrap()
            .into_inner();
        let report = rfcl_proto::v1::EpisodeReport {
            lease_id: lease.lease_id,
            success_at_end: true,
            success_once: true,
            episode_return: 5.0,
            length: 16,
            policy_version: 1,
            stage_epoch: lease.stage_epoch,
            actor_id: 2,
            actor_env_steps: 16,
            policy_env_steps: 0,
            // One simulator worker restart, reported with every episode: counted once.
            actor_sim_restarts: 1,
            reset_failure: String::new(),
        };
        client.report(report).await.unwrap();
    }

    let dom = dump_dom(&dir.path().join("profile"), &server.dashboard);
    assert_eq!(
        dom.matches("class=\"demo-bar\"").count(),
        3,
        "one bar row per demo:\n{dom}"
    );
    assert!(dom.contains("<svg"), "charts are inline SVG");
    assert!(dom.contains("demo 2"), "the bar chart labels the demos");
    assert!(
        dom.contains("Frontiers over env steps") && dom.contains("eval success at end"),
        "the per-demo frontier chart and the progress legend under its chart"
    );
    assert!(dom.contains("stage <b>1</b>"));
    assert!(
        dom.contains("No learner has announced itself yet"),
        "the learner panel, before any learner subscribed"
    );
    assert!(!dom.contains("chart failed"));

    // A screenshot renders too (the README's picture is made the same way).
    let shot = dir.path().join("dashboard.png");
    let status = rfcl_testkit::child::output(
        headless(&dir.path().join("profile2"))
            .arg(format!("--screenshot={}", shot.display()))
            .arg("--window-size=900,1400")
            .arg(&server.dashboard),
    )
    .status;
    assert!(status.success());
    let png = std::fs::read(&shot).unwrap();
    assert!(
        png.starts_with(b"\x89PNG") && png.len() > 10_000,
        "a real screenshot, {} bytes",
        png.len()
    );

    // /api/state and /metrics describe the same state.
    let get = |path: &str| server.dashboard_get(path);
    let view: rfcl_curriculum::dashboard::DashboardView =
        serde_json::from_str(&get("api/state")).unwrap();
    assert_eq!((view.run.episodes, view.run.sim_worker_restarts), (30, 1));
    let metrics = get("metrics");
    assert!(
        metrics.contains("rfcl_curriculum_episodes_total 30"),
        "{metrics}"
    );
    assert!(
        metrics.contains("rfcl_curriculum_sim_worker_restarts_total 1"),
        "{metrics}"
    );
    assert!(metrics.contains("rfcl_curriculum_leases_granted_total 30"));
}
