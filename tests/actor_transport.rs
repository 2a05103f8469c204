//! The actor's transport, with the real binaries: a curriculum server, a learner and one PointMaze
//! actor as child processes on this host, the actor forced to each transport in turn
//! (`--transport shm`, `--transport grpc`). The learner's own counters (Health) show which way the
//! transitions came, the curriculum server's that leases and reports went over gRPC either way,
//! and the actor's log names its choice. `--transport shm` against a learner that serves no shared
//! memory is a clear error.
mod train_support;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use rfcl_testkit::child::{self, ChildGuard};
use train_support::*;

/// Starts service `program ARGS` (a binary rfcl-testkit found or built) and returns it with the
/// value of `field=` on its ready line.
fn start_service(
    name: &str,
    program: std::path::PathBuf,
    args: &[&str],
) -> (ChildGuard, child::ReadyLine) {
    let mut cmd = Command::new(program);
    cmd.args(args)
        .env("RFCL_TOKEN", TEST_TOKEN)
        .env("OMP_WAIT_POLICY", "PASSIVE");
    child::start_service(name, &mut cmd)
}

struct Services {
    _curriculum: ChildGuard,
    _learner: ChildGuard,
    processes: serde_json::Value,
    dir: tempfile::TempDir,
}

fn start_services(learner_extra: &[&str]) -> Services {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let demos = generate_demos(dir.path());
    let config = test_config();
    let run = dir.path().join("run");
    let (config, demos, run) = (
        config.to_str().unwrap().to_string(),
        demos.to_str().unwrap().to_string(),
        run.to_str().unwrap().to_string(),
    );
    let (curriculum, cur_ready) = start_service(
        "curriculum-server",
        rfcl_testkit::binaries::curriculum_server(),
        &["--config", &config, "--demos", &demos, "--run-dir", &run],
    );
    let cur_url = format!("http://{}", cur_ready.expect_field("grpc"));
    let mut args = vec![
        "--config",
        &config,
        "--demos",
        &demos,
        "--run-dir",
        &run,
        "--curriculum",
        &cur_url,
        "--threads",
        "1",
    ];
    args.extend_from_slice(learner_extra);
    let (learner, ready) = start_service("learner", rfcl_testkit::binaries::learner(), &args);
    let processes = serde_json::json!({
        "learner": format!("http://{}", ready.expect_field("grpc")),
        "curriculum": cur_url,
        "dashboard": cur_ready.expect_field("dashboard"),
    });
    Services {
        _curriculum: curriculum,
        _learner: learner,
        processes,
        dir,
    }
}

fn start_actor(s: &Services, transport: &str, log: &Path) -> ChildGuard {
    let mut cmd = Command::new(rfcl_testkit::binaries::actor());
    cmd.args(["--connect", s.processes["learner"].as_str().unwrap()])
        .args(["--envs", "2", "--id", "0", "--retry-for", "10"])
        .args(["--transport", transport])
        .env("RFCL_TOKEN", TEST_TOKEN)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap());
    ChildGuard::new("actor", child::spawn_locked(&mut cmd).unwrap())
}

/// Runs one actor with `--transport transport` until the learner has taken 1,000 transitions
/// and the curriculum server has seen episodes; returns the learner's Health then.
fn run_actor(transport: &str) -> (rfcl_proto::v1::HealthReply, String) {
    let s = start_services(&[]);
    let log = s.dir.path().join("actor.log");
    let mut actor = start_actor(&s, transport, &log);
    let health = wait_for(Duration::from_secs(180), || {
        let h = learner_health(&s.processes)?;
        let episodes = curriculum_state(&s.processes)?["episodes"].as_u64()?;
        (h.env_steps >= 1000 && episodes > 0).then_some(h)
    })
    .unwrap_or_else(|| {
        panic!(
            "no progress over {transport}; actor log:\n{}",
            std::fs::read_to_string(&log).unwrap_or_default()
        )
    });
    assert!(actor.try_wait().unwrap().is_none(), "the actor is alive");
    actor.signal(child::Signal::TERM);
    let status = actor.wait().unwrap();
    assert!(status.success(), "actor exit {status}");
    (health, std::fs::read_to_string(&log).unwrap())
}

#[test]
fn an_actor_forced_to_shared_memory_sends_every_transition_that_way() {
    let (h, log) = run_actor("shm");
    assert!(h.shm_records >= 1000, "{h:?}");
    assert_eq!(h.grpc_records, 0, "{h:?}");
    assert_eq!((h.shm_lost_records, h.refused_batches), (0, 0), "{h:?}");
    assert!(log.contains("transport: shared memory"), "{log}");
}

#[test]
fn an_actor_forced_to_grpc_sends_every_transition_that_way() {
    let (h, log) = run_actor("grpc");
    assert!(h.grpc_records >= 1000, "{h:?}");
    assert_eq!(h.shm_records, 0, "{h:?}");
    assert_eq!(h.refused_batches, 0, "{h:?}");
    assert!(log.contains("transport: gRPC (--transport grpc)"), "{log}");
}

#[test]
fn forcing_shared_memory_without_it_is_a_clear_error() {
    let s = start_services(&["--no-shm"]);
    let log = s.dir.path().join("actor.log");
    let mut actor = start_actor(&s, "shm", &log);
    let status = actor.wait().unwrap();
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(!status.success());
    assert!(
        text.contains(
            "error: actor 0: --transport shm: the learner serves no shared-memory services"
        ),
        "{text}"
    );
    // The learner still serves gRPC.
    assert!(learner_health(&s.processes).is_some());
}
