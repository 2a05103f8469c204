//! The learner's logs as their consumers read them: Prometheus `/metrics` scraped over HTTP while
//! the learner trains (`--metrics-port 0`, URL on the ready line), and the TensorBoard event files
//! read back with TensorBoard's own `EventAccumulator` (the venv's `tensorboard`, from
//! python/requirements.txt), holding exactly the values `metrics.csv` got.
mod service_support;

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use rfcl_learner::tensorboard::EventWriter;
use service_support::*;

const W: u64 = 8;
const STEPS: u64 = 1000;
const PUSHED: u64 = 48;

fn python() -> PathBuf {
    let python = Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing (scripts/setup.sh creates the venv)",
        python.display()
    );
    python
}

/// Every scalar TensorBoard's `EventAccumulator` reads from the event files in `dir`:
/// tag -> [(step, value)] in file order.
fn tensorboard_scalars(dir: &Path) -> BTreeMap<String, Vec<(u64, f64)>> {
    const SCRIPT: &str = r#"
import json, sys
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
acc = EventAccumulator(sys.argv[1], size_guidance={"scalars": 0})
acc.Reload()
print(json.dumps({t: [[e.step, e.value] for e in acc.Scalars(t)] for t in acc.Tags()["scalars"]}))
"#;
    // Needs the venv's tensorboard (python/requirements.txt).
    let out = rfcl_testkit::child::succeed(Command::new(python()).args(["-c", SCRIPT]).arg(dir));
    serde_json::from_str(&out).unwrap()
}

/// `GET /metrics` over a plain HTTP/1.1 connection: (status line, body).
fn scrape(url: &str) -> (String, String) {
    let addr = url
        .strip_prefix("http://")
        .and_then(|rest| rest.strip_suffix("/metrics"))
        .unwrap_or_else(|| panic!("unexpected metrics URL {url}"));
    let mut stream = std::net::TcpStream::connect(addr).unwrap();
    write!(
        stream,
        "GET /metrics HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    let (head, body) = response.split_once("\r\n\r\n").unwrap();
    (head.lines().next().unwrap().to_string(), body.to_string())
}

/// The value of the sample named exactly `name` (with its labels) in an exposition text.
fn sample(body: &str, name: &str) -> f64 {
    body.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' '))
        .unwrap_or_else(|| panic!("no sample {name} in:\n{body}"))
        .parse()
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_endpoint_while_training_and_tensorboard_events_equal_to_metrics_csv() {
    let dir = tempfile::tempdir().unwrap();
    let run_dir = dir.path().join("run");
    let demos = write_demos(dir.path());
    let config = write_config(dir.path(), W, STEPS, "");
    let curriculum = Curriculum::start(&config, &demos, &run_dir);

    let mut args: Vec<std::ffi::OsString> = vec![
        "--threads".into(),
        "1".into(),
        "--metrics-port".into(),
        "0".into(),
    ];
    args.extend(Learner::args(&config, &curriculum.grpc, &demos, &run_dir));
    let args: Vec<&std::ffi::OsStr> = args.iter().map(std::ffi::OsString::as_os_str).collect();
    let (mut learner, ready) = Learner::start_command(&mut learner_command(&args));
    let metrics_url = ready.expect_field("metrics").to_string();
    let mut client = learner.client().await;

    push(&mut client, batches(0..PUSHED, 8, 0)).await.unwrap();
    let iterations = earned(PUSHED, W);
    wait_health(&mut client, Duration::from_secs(60), |h| {
        h.env_steps == PUSHED && h.updates == G * iterations
    })
    .await;

    // The status is refreshed after each iteration, so it already shows the last one.
    let (status, body) = scrape(&metrics_url);
    assert!(status.contains("200"), "{status}");
    assert_eq!(sample(&body, "rfcl_learner_env_steps_total"), PUSHED as f64);
    assert_eq!(
        sample(&body, "rfcl_learner_critic_updates_total"),
        (G * iterations) as f64
    );
    assert_eq!(
        sample(&body, "rfcl_learner_iterations_total"),
        iterations as f64
    );
    assert_eq!(
        sample(&body, "rfcl_learner_policy_version"),
        (1 + iterations) as f64
    );
    assert_eq!(
        sample(&body, "rfcl_learner_utd_target"),
        G as f64 / K as f64
    );
    assert_eq!(
        sample(&body, "rfcl_learner_replay_transitions{buffer=\"online\"}"),
        PUSHED as f64
    );
    assert_eq!(
        sample(&body, "rfcl_learner_replay_transitions{buffer=\"offline\"}"),
        (DEMOS * DEMO_LEN) as f64
    );
    // capacity 1000 over 2 envs: 500 slots each; record = 4 * (2 * 4 + 2 + 2) bytes.
    assert_eq!(
        sample(&body, "rfcl_learner_replay_bytes{buffer=\"online\"}"),
        (1000 * 4 * (2 * OBS + ACT + 2)) as f64
    );
    assert_eq!(
        sample(
            &body,
            "rfcl_learner_dropped_records_total{reason=\"stale_epoch\"}"
        ),
        0.0
    );
    assert!(
        sample(
            &body,
            "rfcl_learner_time_seconds_total{activity=\"update\"}"
        ) > 0.0
    );
    assert!(sample(&body, "rfcl_learner_resident_memory_bytes") > 1e6);
    assert_eq!(
        sample(
            &body,
            "rfcl_learner_ingest_records_total{transport=\"grpc\"}"
        ),
        PUSHED as f64
    );

    assert!(learner.sigterm().success());

    // TensorBoard reads one point per metrics.csv row and column, with the same value.
    let csv = std::fs::read_to_string(run_dir.join("metrics.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert!(rows.len() >= 2, "{csv}");
    let tb = tensorboard_scalars(&run_dir);
    for (col, tag) in header.iter().enumerate().skip(1) {
        let expected: Vec<(u64, f64)> = rows
            .iter()
            .filter(|r| !r[col].is_empty())
            .map(|r| (r[0].parse().unwrap(), r[col].parse().unwrap()))
            .collect();
        let got = tb.get(*tag).cloned().unwrap_or_default();
        assert_eq!(got.len(), expected.len(), "{tag}: {got:?} vs {expected:?}");
        for ((gs, gv), (es, ev)) in got.iter().zip(&expected) {
            assert_eq!(gs, es, "{tag}");
            assert_eq!(*gv as f32, *ev as f32, "{tag} at step {es}");
        }
    }
    assert!(tb.contains_key("train/critic/critic_loss"), "{tb:?}");
    assert!(!tb.contains_key("env_steps"));
}

#[test]
fn a_resumed_session_replaces_the_points_after_its_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let mut first = EventWriter::create(dir.path(), None).unwrap();
    for step in [100u64, 200, 300] {
        first
            .scalars(step, [("time/SPS", step as f64), ("train/critic/q", 1.0)])
            .unwrap();
    }
    drop(first);
    // Resumed from the checkpoint at step 200: the point at 300 is orphaned.
    let mut resumed = EventWriter::create(dir.path(), Some(200)).unwrap();
    resumed.scalars(250, [("time/SPS", 2.5)]).unwrap();
    drop(resumed);

    let tb = tensorboard_scalars(dir.path());
    assert_eq!(tb["time/SPS"], vec![(100, 100.0), (200, 200.0), (250, 2.5)]);
    assert_eq!(tb["train/critic/q"], vec![(100, 1.0), (200, 1.0)]);
}
