//! The replay loop of the fuzz regression tests (core, proto and shm `tests/fuzz_regressions.rs`,
//! each including this file by `#[path]`): every committed input through a target's body, on
//! stable Rust without libFuzzer (docs/FUZZING.md).
use std::path::{Path, PathBuf};

/// The files of `fuzz/<kind>/<target>/` (kind: `corpus` or `artifacts`), sorted; none when the
/// directory does not exist. `manifest_dir` is the including crate's `CARGO_MANIFEST_DIR`.
pub fn inputs(manifest_dir: &str, kind: &str, target: &str) -> Vec<PathBuf> {
    let dir = Path::new(manifest_dir)
        .join("../fuzz")
        .join(kind)
        .join(target);
    let mut files: Vec<PathBuf> = match std::fs::read_dir(&dir) {
        Ok(entries) => entries
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .collect(),
        Err(_) => Vec::new(),
    };
    files.sort();
    files
}

/// Fails unless the corpus of `target` has at least `min` files: an empty replay proves nothing.
pub fn non_empty(target: &str, files: &[PathBuf], min: usize) {
    assert!(
        files.len() >= min,
        "fuzz/corpus/{target}/ has {} files: the replay would prove nothing",
        files.len()
    );
}

/// Runs every input through `run`; fails naming each input that panicked or whose rejection
/// `names_it` finds vague. Returns the number of rejections.
pub fn replay(
    files: &[PathBuf],
    run: fn(&[u8]) -> Vec<String>,
    names_it: fn(&str) -> bool,
) -> usize {
    let mut failures = Vec::new();
    let mut rejections = 0;
    for file in files {
        let data = std::fs::read(file).unwrap();
        match std::panic::catch_unwind(|| run(&data)) {
            Ok(refused) => {
                rejections += refused.len();
                for r in refused {
                    if !names_it(&r) {
                        failures.push(format!("{}: vague rejection {r:?}", file.display()));
                    }
                }
            }
            Err(_) => failures.push(format!("{}: panicked", file.display())),
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
    rejections
}
