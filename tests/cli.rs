//! The `rfcl` command as a user runs it: help, config resolution of every preset, and one clear
//! error line (non-zero exit) for a misspelt key and for a corrupt demo file.
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn rfcl(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rfcl"))
        .args(args)
        .output()
        .expect("running rfcl")
}

fn error_lines(out: &Output) -> Vec<String> {
    String::from_utf8_lossy(&out.stderr)
        .lines()
        .filter(|l| l.starts_with("error:"))
        .map(str::to_string)
        .collect()
}

/// `rfcl ARGS`, which must fail with exactly one `error:` line: that line.
fn error_line(args: &[&str]) -> String {
    let out = rfcl(args);
    assert!(!out.status.success());
    let lines = error_lines(&out);
    assert_eq!(lines.len(), 1, "{lines:?}");
    lines.into_iter().next().unwrap()
}

fn yaml_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            yaml_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "yml") {
            out.push(path);
        }
    }
}

#[test]
fn help_lists_the_subcommands() {
    let out = rfcl(&["--help"]);
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    for sub in ["train", "demos", "eval", "bench", "config"] {
        assert!(
            help.lines().any(|l| l.trim_start().starts_with(sub)),
            "`{sub}` missing from:\n{help}"
        );
    }
}

#[test]
fn every_preset_resolves_with_config_show() {
    let mut files = Vec::new();
    yaml_files(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("configs"),
        &mut files,
    );
    assert!(
        files.len() > 40,
        "presets for every suite and task, both sets"
    );
    for file in files {
        let out = rfcl(&["config", "show", file.to_str().unwrap()]);
        assert!(
            out.status.success(),
            "{}: {}",
            file.display(),
            String::from_utf8_lossy(&out.stderr)
        );
        let yaml = String::from_utf8_lossy(&out.stdout);
        assert!(yaml.contains("reverse:") && yaml.contains("forward:") && yaml.contains("sac:"));
    }
}

#[test]
fn overrides_apply() {
    let cfg = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/pointmaze.yml");
    let out = rfcl(&[
        "config",
        "show",
        cfg,
        "sac.batch_size=128",
        "network.actor_features=[64,64]",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let yaml = String::from_utf8_lossy(&out.stdout);
    assert!(yaml.contains("batch_size: 128"), "{yaml}");
}

#[test]
fn a_misspelt_key_is_one_clear_error_line() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("typo.yml");
    std::fs::write(&file, "sac:\n  batch_sise: 512\n").unwrap();
    let line = error_line(&["config", "show", file.to_str().unwrap()]);
    let expected = [
        "typo.yml",
        "sac.batch_sise",
        "did you mean 'sac.batch_size'",
    ];
    rfcl_testkit::assert_contains_all(&line, &expected);

    let cfg = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/pointmaze.yml");
    let line = error_line(&["config", "show", cfg, "sac.tau=7"]);
    assert!(line.contains("sac.tau"), "{line}");
}

#[test]
fn a_corrupt_demo_file_is_one_clear_error_line() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("demos.h5");
    std::fs::write(&file, "this is not an HDF5 file\n").unwrap();
    let line = error_line(&["demos", "inspect", file.to_str().unwrap()]);
    assert!(
        line.contains("demos.h5") && line.to_lowercase().contains("hdf5"),
        "{line}"
    );

    let out = rfcl(&[
        "demos",
        "inspect",
        dir.path().join("missing.h5").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(error_lines(&out)[0].contains("missing.h5"));
}

/// A damaged file that crashes libhdf5 itself (a fuzzing reproducer): `rfcl` reads demos in a
/// child first, so the user gets one error line naming the file instead of a segmentation fault.
#[test]
fn a_demo_file_that_crashes_the_hdf5_library_is_one_clear_error_line() {
    let dir = tempfile::tempdir().unwrap();
    let file = rfcl_testkit::demos::hdf5_crash_reproducer(dir.path());
    let line = error_line(&["demos", "inspect", file.to_str().unwrap()]);
    rfcl_testkit::assert_contains_all(&line, &["damaged.h5", "crashed the HDF5 library"]);
    // `rfcl train` refuses it before any service starts.
    let line = error_line(&[
        "train",
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("configs/pointmaze_test.yml")
            .to_str()
            .unwrap(),
        &format!("train.dataset_path={}", file.display()),
        "--run-dir",
        dir.path().join("run").to_str().unwrap(),
    ]);
    rfcl_testkit::assert_contains_all(&line, &["train.dataset_path", "crashed the HDF5 library"]);
    assert!(!dir.path().join("run").join("processes.json").exists());
}

/// `rfcl demos generate --env pointmaze -n N --out OUT`, which must succeed.
fn generate_pointmaze(n: u32, out: &Path) {
    let n = n.to_string();
    let out = rfcl(&[
        "demos",
        "generate",
        "--env",
        "pointmaze",
        "-n",
        &n,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn generated_pointmaze_demos_inspect_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("pm.h5");
    generate_pointmaze(3, &file);
    let out = rfcl(&["demos", "inspect", file.to_str().unwrap()]);
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("episodes: 3 (3 successful)") && text.contains("obs 7, action 2"),
        "{text}"
    );
    // The quality check replays each demo in PointMaze: all three pass.
    let out = rfcl(&["demos", "inspect", file.to_str().unwrap(), "--replay"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
    assert_eq!(text.matches(": ok (").count(), 3, "{text}");
    assert!(
        text.contains("3 of 3 demos pass the replay check"),
        "{text}"
    );
}

/// A demo state the env cannot start from (PointMaze's collision flag at 50) is found when the
/// file is read, before any run: `rfcl demos inspect` names the demo, the state and the field and
/// exits 1, and `rfcl train` refuses the file before any process starts.
#[test]
fn a_bad_demo_state_is_refused_when_the_file_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("pm.h5");
    generate_pointmaze(2, &good);
    let out = rfcl(&["demos", "inspect", good.to_str().unwrap()]);
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout)
        .contains("every state of every demo is a valid reset state"));

    let bad = dir.path().join("bad.h5");
    let mut set = {
        let _guard = rfcl_testkit::hdf5::fork_guard();
        rfcl_core::demo::DemoSet::load(&good).unwrap()
    };
    let dim = set.state_dim;
    set.demos[1].env_states[5 * dim + dim - 1] = 50.0;
    let episode = set.demos[1].episode_id;
    rfcl_testkit::demos::write_demo_set(&set, &bad);
    let out = rfcl(&["demos", "inspect", bad.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{text}");
    assert!(
        text.contains(&format!(
            "demo 1 (episode {episode}) state 5 is not a valid reset state: "
        )) && text.contains("50 is neither 0 nor 1"),
        "{text}"
    );
    let run_dir = dir.path().join("run");
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/pointmaze_test.yml");
    let out = rfcl(&[
        "train",
        config.to_str().unwrap(),
        &format!("train.dataset_path={}", bad.display()),
        "--run-dir",
        run_dir.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains(&format!(
            "demo 1 (episode {episode}) state 5 is not a valid reset state"
        )),
        "{err}"
    );
    assert!(!run_dir.exists(), "nothing started");
}

#[test]
fn unbuilt_subcommands_say_so_and_fail() {
    let out = rfcl(&[
        "demos",
        "generate",
        "--env",
        "reach-v3",
        "--out",
        "/tmp/never.h5",
    ]);
    assert!(!out.status.success());
    assert!(error_lines(&out)[0].contains("not built yet"));
}
