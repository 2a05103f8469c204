//! `rfcl train` when something is wrong: a clear error and a non-zero exit, and no child process
//! left behind. Bad input is refused before any process starts; a service that fails at start-up
//! or dies mid-run stops the run with that service's error.
mod train_support;

use std::process::Command;
use std::time::Duration;

use train_support::*;

fn rfcl_train(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_rfcl"))
        .arg("train")
        .args(args)
        .output()
        .unwrap()
}

fn error_line(out: &std::process::Output) -> String {
    String::from_utf8_lossy(&out.stderr)
        .lines()
        .find(|l| l.starts_with("error:"))
        .unwrap_or_else(|| panic!("no error line in {}", String::from_utf8_lossy(&out.stderr)))
        .to_string()
}

#[test]
fn no_demos_is_refused_before_anything_starts() {
    let dir = tempfile::tempdir().unwrap();
    let run_dir = dir.path().join("run");
    let config = test_config();
    let out = rfcl_train(&[
        config.to_str().unwrap(),
        "--run-dir",
        run_dir.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let line = error_line(&out);
    assert!(
        line.contains("train.dataset_path is not set") && line.contains("rfcl demos generate"),
        "{line}"
    );
    assert!(!run_dir.exists(), "nothing was created");

    let out = rfcl_train(&[
        config.to_str().unwrap(),
        "train.dataset_path=/nonexistent/demos.h5",
        "--run-dir",
        run_dir.to_str().unwrap(),
    ]);
    assert!(error_line(&out).contains("demo file /nonexistent/demos.h5 not found"));

    let out = rfcl_train(&[
        config.to_str().unwrap(),
        "--resume",
        dir.path().to_str().unwrap(),
    ]);
    assert!(error_line(&out).contains("is not a run directory to resume"));
}

#[test]
fn a_service_that_fails_at_start_stops_the_run_with_its_error() {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let bogus = dir.path().join("demos.h5");
    std::fs::write(&bogus, "not an HDF5 file\n").unwrap();
    let run_dir = dir.path().join("run");
    let out = rfcl_train(&[
        test_config().to_str().unwrap(),
        &format!("train.dataset_path={}", bogus.display()),
        "--run-dir",
        run_dir.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    // The curriculum server loads the demos first: its exit and the tail of its log.
    assert!(
        stderr.contains("curriculum-server exited before it was ready (exit status 1)")
            && stderr.contains("logs/curriculum-server.log (last lines)")
            && stderr.contains("demos.h5"),
        "{stderr}"
    );
    assert!(!run_dir.join("processes.json").exists());
}

#[test]
fn a_learner_that_dies_mid_run_stops_the_run_and_every_child() {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let demos = generate_demos(dir.path());
    let run_dir = dir.path().join("run");
    let mut training = Training::start(
        &[
            test_config().display().to_string(),
            format!("train.dataset_path={}", demos.display()),
            "--run-dir".into(),
            run_dir.display().to_string(),
        ],
        &run_dir,
        &dir.path().join("rfcl.stderr"),
    );
    let processes = training.processes(Duration::from_secs(120));
    wait_for(Duration::from_secs(120), || {
        learner_health(&processes).filter(|h| h.env_steps > 1000)
    })
    .unwrap_or_else(|| panic!("the learner never got data:\n{}", training.stderr()));
    signal(
        child_pid(&processes, "learner") as u32,
        rustix::process::Signal::KILL,
    );
    let status = training.wait(Duration::from_secs(120));
    let stderr = training.stderr();
    assert_eq!(status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("error: the learner exited (killed by signal 9)"),
        "{stderr}"
    );
    for pid in child_pids(&processes) {
        assert!(!alive(pid), "child {pid} outlived the run");
    }
}
