//! The service binaries a test runs as children, found next to the test executable.
//!
//! Cargo builds a test executable into `target/<profile>/deps/` and the workspace's binaries into
//! `target/<profile>/`, but it builds only the binaries of the package under test: a learner test
//! that starts a curriculum server, or a launcher test that runs `rfcl train`, needs binaries of
//! other packages, which no Cargo dependency may provide (services meet only over the wire,
//! docs/DESIGN.md). So a missing binary is built here, with the cargo that runs the tests
//! (`$CARGO`), in the same profile and target directory:
//! `cargo build -p <package> --bin <name> [--release | --profile P]`. With
//! `RFCL_TESTKIT_NO_BUILD=1` nothing is built and a missing binary fails the test with that
//! command. A binary that is present is used as it is: `cargo nextest run --workspace` (or
//! `cargo build --workspace`) keeps them all fresh.
//!
//! A package's own binaries are better reached with `env!("CARGO_BIN_EXE_<name>")`, which cargo
//! guarantees are built for its tests.
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Mutex;

/// The `curriculum-server` binary (package `rfcl-curriculum`).
pub fn curriculum_server() -> PathBuf {
    service_binary("rfcl-curriculum", "curriculum-server")
}

/// The `learner` binary (package `rfcl-learner`).
pub fn learner() -> PathBuf {
    service_binary("rfcl-learner", "learner")
}

/// The `actor` binary (package `rfcl-actor`).
pub fn actor() -> PathBuf {
    service_binary("rfcl-actor", "actor")
}

/// The Python simulator worker the actor starts, `rfcl-sim-worker` (package `rfcl-actor`).
pub fn sim_worker() -> PathBuf {
    service_binary("rfcl-actor", "rfcl-sim-worker")
}

/// Binary `bin` of workspace package `package` in this test's profile directory, built first
/// when it is missing.
pub fn service_binary(package: &str, bin: &str) -> PathBuf {
    let layout = Layout::of_current_exe();
    let path = layout.profile_dir.join(bin);
    if path.is_file() {
        return path;
    }
    // One build at a time from this process; cargo's own lock orders the others.
    static BUILDING: Mutex<()> = Mutex::new(());
    let _one = BUILDING.lock().unwrap_or_else(|p| p.into_inner());
    if path.is_file() {
        return path;
    }
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let args = layout.build_args(package, bin);
    // What to run by hand: the same build, by whatever cargo is on the PATH.
    let shown = format!("cargo {}", args.join(" "));
    if std::env::var_os("RFCL_TESTKIT_NO_BUILD").is_some() {
        panic!(
            "{} is not built (RFCL_TESTKIT_NO_BUILD is set): run `{shown}` in {}",
            path.display(),
            workspace_root().display()
        );
    }
    eprintln!(
        "rfcl-testkit: {} is missing; running `{shown}`",
        path.display()
    );
    // The `--manifest-path` and `CARGO_TARGET_DIR` keep the build in this workspace and this
    // target directory whatever the test's working directory is.
    let status = crate::child::spawn_locked(
        Command::new(&cargo)
            .args(&args)
            .arg("--manifest-path")
            .arg(workspace_root().join("Cargo.toml"))
            .env("CARGO_TARGET_DIR", &layout.target_dir),
    )
    .and_then(|mut child| child.wait());
    match status {
        Ok(status) if status.success() && path.is_file() => path,
        Ok(status) => panic!(
            "building {bin} failed ({status}); {} is needed by this test: run `{shown}` in {}",
            path.display(),
            workspace_root().display()
        ),
        Err(e) => panic!(
            "could not run cargo ({e}) to build {}: run `{shown}` in {}",
            path.display(),
            workspace_root().display()
        ),
    }
}

/// The workspace root (this crate's parent directory).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("testkit/ lies in the workspace root")
        .to_path_buf()
}

/// Where the running test executable sits in cargo's target directory.
struct Layout {
    /// `target/<profile>` or `target/<triple>/<profile>`.
    profile_dir: PathBuf,
    /// `target`.
    target_dir: PathBuf,
    /// `<triple>` when cargo was given `--target`.
    triple: Option<String>,
}

impl Layout {
    fn of_current_exe() -> Layout {
        let exe = std::env::current_exe().expect("the test executable's path");
        let mut dir = exe.parent().expect("a directory").to_path_buf();
        // Test executables live in <profile>/deps, binaries in <profile>.
        if dir.file_name().is_some_and(|n| n == "deps") {
            dir.pop();
        }
        let parent = dir.parent().unwrap_or(Path::new("/")).to_path_buf();
        // cargo marks the target directory's root with CACHEDIR.TAG; one level more when a
        // target triple was given.
        let (target_dir, triple) = if !parent.join("CACHEDIR.TAG").exists()
            && parent
                .parent()
                .is_some_and(|p| p.join("CACHEDIR.TAG").exists())
        {
            let triple = parent.file_name().map(|n| n.to_string_lossy().into_owned());
            (parent.parent().unwrap().to_path_buf(), triple)
        } else {
            (parent, None)
        };
        Layout {
            profile_dir: dir,
            target_dir,
            triple,
        }
    }

    /// `build -p PACKAGE --bin BIN` with the flags that select this profile (and target).
    fn build_args(&self, package: &str, bin: &str) -> Vec<String> {
        let mut args = vec![
            "build".to_string(),
            "-p".into(),
            package.into(),
            "--bin".into(),
            bin.into(),
        ];
        match self.profile_dir.file_name().and_then(|n| n.to_str()) {
            Some("debug") => {}
            Some("release") => args.push("--release".into()),
            Some(other) => args.extend(["--profile".into(), other.into()]),
            None => {}
        }
        if let Some(triple) = &self.triple {
            args.extend(["--target".into(), triple.clone()]);
        }
        args
    }
}
