//! `rfcl train` when something is wrong: a clear error and a non-zero exit, and no child process
//! left behind. Bad input is refused before any process starts; a service that fails at start-up,
//! or keeps dying mid-run, stops the run with that service's error; Ctrl-C while the services
//! start stops them; a SIGINT the parent left ignored stays ignored, and SIGTERM stops the run; a
//! second owner of a running run's directory is refused.
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
        "--learner-threads",
        "0",
        "--run-dir",
        run_dir.to_str().unwrap(),
    ]);
    assert!(
        error_line(&out).contains("--learner-threads must be at least 1, got 0"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
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
    let demos = generate_demos(dir.path());
    // The curriculum server's port is taken: it fails at start-up, after rfcl's own checks.
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let run_dir = dir.path().join("run");
    let out = rfcl_train(&[
        test_config().to_str().unwrap(),
        &format!("train.dataset_path={}", demos.display()),
        &format!("service.curriculum_port={port}"),
        "--run-dir",
        run_dir.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    // Its exit and the tail of its log, which names the port.
    assert!(
        stderr.contains("curriculum-server exited before it was ready (exit status 1)")
            && stderr.contains("logs/curriculum-server.log (last lines)")
            && stderr.contains(&port.to_string()),
        "{stderr}"
    );
    assert!(!run_dir.join("processes.json").exists());
}

/// Processes (other than this test) whose command line names `run_dir`.
fn processes_of(run_dir: &std::path::Path) -> Vec<(u32, String)> {
    let needle = run_dir.display().to_string();
    let mut found = Vec::new();
    for entry in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let Ok(raw) = std::fs::read(entry.path().join("cmdline")) else {
            continue;
        };
        let cmdline = String::from_utf8_lossy(&raw).replace('\0', " ");
        if cmdline.contains(&needle) {
            found.push((pid, cmdline));
        }
    }
    found
}

#[test]
fn ctrl_c_while_the_learner_starts_leaves_no_child_behind() {
    let dir = tempfile::tempdir().unwrap();
    let mut training = start_test_run(dir.path(), &[], "rfcl.stderr");
    let run_dir = training.run_dir.clone();
    // The learner has been started (its log exists) but the session has not (no processes.json).
    wait_for(Duration::from_secs(120), || {
        run_dir.join("logs/learner.log").exists().then_some(())
    })
    .unwrap_or_else(|| panic!("the learner was not started:\n{}", training.stderr()));
    signal(training.pid(), rustix::process::Signal::INT);
    let status = training.wait(Duration::from_secs(60));
    assert!(!status.success(), "{}", training.stderr());
    let left = wait_for(Duration::from_secs(10), || {
        let left = processes_of(&run_dir);
        left.is_empty().then_some(())
    });
    assert!(
        left.is_some(),
        "children outlived rfcl: {:?}\n{}",
        processes_of(&run_dir),
        training.stderr()
    );
}

#[test]
fn a_learner_that_keeps_dying_stops_the_run_with_a_failed_summary() {
    let dir = tempfile::tempdir().unwrap();
    let mut training = start_test_run(dir.path(), &[], "rfcl.stderr");
    let run_dir = training.run_dir.clone();
    let mut processes = training.processes(Duration::from_secs(120));
    let mut killed = Vec::new();
    // Three deaths are restarted; the fourth within the window stops the run.
    for round in 0..4 {
        let pid = wait_for(Duration::from_secs(120), || {
            let p: serde_json::Value = serde_json::from_str(
                &std::fs::read_to_string(run_dir.join("processes.json")).ok()?,
            )
            .ok()?;
            let pid = child_pid(&p, "learner");
            if killed.contains(&pid) {
                return None;
            }
            learner_health(&p)?;
            processes = p;
            Some(pid)
        })
        .unwrap_or_else(|| panic!("no learner in round {round}:\n{}", training.stderr()));
        signal(pid as u32, rustix::process::Signal::KILL);
        killed.push(pid);
    }
    let status = training.wait(Duration::from_secs(120));
    let stderr = training.stderr();
    assert_eq!(status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("the learner died 4 times within 600 s (last: killed by signal 9)"),
        "{stderr}"
    );
    assert_eq!(stderr.matches("the learner is back").count(), 3, "{stderr}");
    let summary = training.summary();
    assert_eq!(summary["ending"], "failed");
    assert!(
        summary["error"]
            .as_str()
            .unwrap()
            .contains("the learner died 4 times"),
        "{summary}"
    );
    assert_eq!(summary["service_restarts"].as_array().unwrap().len(), 3);
    for pid in child_pids(&processes) {
        assert!(!alive(pid), "child {pid} outlived the run");
    }
}

/// Started as a shell script's background job is (SIGINT ignored), rfcl keeps ignoring SIGINT for
/// the whole run, as the Unix convention has it, so that when the interrupt comes does not decide
/// what it does; SIGTERM stops the run cleanly, with its summary, and no child outlives it.
#[test]
fn an_ignored_sigint_stays_ignored_and_sigterm_stops_the_run() {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let demos = generate_demos(dir.path());
    let run_dir = dir.path().join("run");
    let args = train_args(&test_config(), &demos, &[], &run_dir);
    let log = dir.path().join("rfcl.stderr");
    let mut training = Training::start_ignoring_sigint(&args, &run_dir, &log);
    // An interrupt while the services start, and one once they all run: both ignored.
    std::thread::sleep(Duration::from_millis(300));
    signal(training.pid(), rustix::process::Signal::INT);
    let processes = training.processes(Duration::from_secs(120));
    signal(training.pid(), rustix::process::Signal::INT);
    std::thread::sleep(Duration::from_secs(5));
    assert!(training.exited().is_none(), "{}", training.stderr());
    assert!(
        child_pids(&processes).into_iter().all(alive),
        "{}",
        training.stderr()
    );
    signal(training.pid(), rustix::process::Signal::TERM);
    let status = training.wait(Duration::from_secs(120));
    assert_eq!(status.code(), Some(130), "{}", training.stderr());
    assert_eq!(training.summary()["ending"], "interrupted");
    let left = wait_for(Duration::from_secs(10), || {
        processes_of(&run_dir).is_empty().then_some(())
    });
    assert!(
        left.is_some(),
        "children outlived rfcl: {:?}",
        processes_of(&run_dir)
    );
}

/// One owner per run directory: while a run trains, a second `rfcl train --resume` of it (another
/// terminal) and a learner or curriculum server started by hand on it are each refused at once,
/// naming the directory and the holder's pid, and the run goes on untouched.
#[test]
fn a_second_owner_of_a_running_run_directory_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut training = start_test_run(dir.path(), &[], "rfcl.stderr");
    let processes = training.processes(Duration::from_secs(120));
    let run_dir = training.run_dir.clone();
    let run = run_dir.display().to_string();

    let second = Command::new(env!("CARGO_BIN_EXE_rfcl"))
        .args(["train", &format!("{run}/config.yml"), "--resume", &run])
        .output()
        .unwrap();
    assert!(!second.status.success());
    let line = error_line(&second);
    assert!(
        line.contains(&format!("{run} is in use by another rfcl"))
            && line.contains(&format!("pid {}", training.pid())),
        "{line}"
    );
    let pid_of = |name: &str| {
        processes["children"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["name"] == name)
            .and_then(|c| c["pid"].as_u64())
            .unwrap()
    };
    let config = format!("{run}/config.yml");
    for (binary, role, args) in [
        (
            rfcl_testkit::binaries::learner(),
            "learner",
            vec![
                "--config",
                &config,
                "--curriculum",
                "http://127.0.0.1:1",
                "--run-dir",
                &run,
            ],
        ),
        (
            rfcl_testkit::binaries::curriculum_server(),
            "curriculum-server",
            vec!["--config", &config, "--resume", &run],
        ),
    ] {
        let out = Command::new(&binary)
            .args(args)
            .env("RFCL_TOKEN_FILE", run_dir.join("token"))
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success()
                && text.contains(&format!("{run} is in use by another {role}"))
                && text.contains(&format!("pid {}", pid_of(role))),
            "{role}: {text}"
        );
    }
    assert!(training.exited().is_none(), "{}", training.stderr());
    signal(training.pid(), rustix::process::Signal::TERM);
    let status = training.wait(Duration::from_secs(120));
    assert_eq!(status.code(), Some(130), "{}", training.stderr());
}

/// A run directory on a filesystem with no room (here a 3 MB tmpfs, mounted in a mount namespace
/// of its own) is refused in one line before any process starts, instead of services dying on
/// their first checkpoint or log line.
#[test]
fn a_run_directory_on_a_full_filesystem_is_refused_before_anything_starts() {
    let dir = tempfile::tempdir().unwrap();
    let demos = generate_demos(dir.path());
    let small = dir.path().join("small");
    std::fs::create_dir(&small).unwrap();
    let run_dir = small.join("run");
    let out = Command::new("unshare")
        .args(["--user", "--map-root-user", "--mount", "sh", "-c"])
        .arg(r#"mount -t tmpfs -o size=3m tmpfs "$1" && shift && exec "$@""#)
        .arg("sh")
        .arg(&small)
        .arg(env!("CARGO_BIN_EXE_rfcl"))
        .arg("train")
        .arg(test_config())
        .arg(format!("train.dataset_path={}", demos.display()))
        .arg("--run-dir")
        .arg(&run_dir)
        .output()
        .unwrap();
    let line = error_line(&out);
    assert!(
        !out.status.success()
            && line.contains(&format!(
                "MiB free on the filesystem of {}",
                run_dir.display()
            ))
            && line.contains("free space or choose another --run-dir"),
        "{line}"
    );
    assert!(
        !String::from_utf8_lossy(&out.stderr).contains("starting"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
