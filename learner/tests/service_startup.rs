//! Start-up failures: a bad config, missing demos, demos that do not fit the config, an
//! unreachable curriculum server, a resume without a checkpoint. Each exits non-zero before the
//! ready line, with one `error:` line on stderr that says what is wrong.
mod service_support;

use std::ffi::OsString;
use std::path::Path;

use service_support::*;

/// Runs the learner and returns its `error:` line (asserting failure and no ready line).
fn failure(args: &[OsString]) -> String {
    let args: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    let (status, stdout, stderr) = run_learner(&args);
    assert!(!status.success(), "expected a failure; stderr:\n{stderr}");
    assert_eq!(stdout, "", "no ready line on failure");
    let errors: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(errors.len(), 1, "one error line; stderr:\n{stderr}");
    errors[0].to_string()
}

/// An address where nothing listens.
fn dead_address() -> String {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    drop(listener);
    format!("http://{addr}")
}

fn args(config: &Path, curriculum: &str, demos: &Path, run_dir: &Path) -> Vec<OsString> {
    let mut args = Learner::args(config, curriculum, demos, run_dir);
    args.extend(["--connect-timeout-s".into(), "2".into()]);
    args
}

#[test]
fn start_up_failures_exit_non_zero_with_one_clear_line() {
    let dir = tempfile::tempdir().unwrap();
    let demos = write_demos(dir.path());
    let config = write_config(dir.path(), 8, 1000, "");
    let run_dir = dir.path().join("run");
    let dead = dead_address();

    // An unknown config key (the override is checked like a file key).
    let mut bad_key = args(&config, &dead, &demos, &run_dir);
    bad_key.push("sac.bogus_key=1".into());
    let line = failure(&bad_key);
    assert!(line.contains("sac.bogus_key"), "{line}");

    // A demo file that is not there.
    let line = failure(&args(
        &config,
        &dead,
        &dir.path().join("missing.h5"),
        &run_dir,
    ));
    assert!(line.contains("missing.h5"), "{line}");

    // A file that crashes libhdf5 itself is named, not a segmentation fault.
    let damaged = rfcl_testkit::demos::hdf5_crash_reproducer(dir.path());
    let line = failure(&args(&config, &dead, &damaged, &run_dir));
    assert!(
        line.contains("damaged.h5") && line.contains("crashed the HDF5 library"),
        "{line}"
    );

    // Demos whose dims differ from the config's.
    let mut dims = args(&config, &dead, &demos, &run_dir);
    dims.push("env.obs_dim=7".into());
    let line = failure(&dims);
    assert!(line.contains("env.obs_dim"), "{line}");

    // No curriculum server.
    let line = failure(&args(&config, &dead, &demos, &run_dir));
    assert!(
        line.contains("cannot reach the curriculum server"),
        "{line}"
    );
    assert!(line.contains(&dead), "{line}");

    // --resume of a directory without a checkpoint.
    let mut resume = args(&config, &dead, &demos, &run_dir);
    let at = resume.iter().position(|a| a == "--run-dir").unwrap();
    resume[at] = "--resume".into();
    let line = failure(&resume);
    assert!(line.contains("no learner checkpoint"), "{line}");
}
