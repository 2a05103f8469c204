//! Curriculum snapshots: the whole [`ServerState`] (curricula, random stream, leases, counters) in a
//! versioned JSON file, replaced atomically. A server restarted with `--resume` from a snapshot
//! hands out exactly what an uninterrupted one would have after that snapshot.
//!
//! | file                              | contents                                            |
//! |-----------------------------------|-----------------------------------------------------|
//! | `curriculum.snapshot.json`        | the newest snapshot                                 |
//! | `curriculum.snapshot.prev.json`   | the one before it: the fallback                     |
//!
//! Damage is detected, never trusted: a snapshot carries the CRC-32C of its own bytes
//! ([`rfcl_core::checksum`]). [`save`] first copies the current snapshot, when intact, to the
//! previous one, then replaces the current one atomically, so a crash at any moment leaves an
//! intact generation. [`load_newest`] gives the current snapshot, or else the previous one with the
//! damage it skipped, and refuses when both are damaged.
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::state::ServerState;

/// Bumped whenever the snapshot's shape changes. Format 1 (before checksums) is still read, with
/// nothing to verify.
pub const SNAPSHOT_FORMAT: u32 = 2;
const FORMAT_V1: u32 = 1;
pub const SNAPSHOT_FILE: &str = "curriculum.snapshot.json";
/// The generation before [`SNAPSHOT_FILE`]'s, kept as the fallback.
pub const PREVIOUS_FILE: &str = "curriculum.snapshot.prev.json";

#[derive(Serialize)]
struct SnapshotFile<'a> {
    format: u32,
    run_name: &'a str,
    checksum: &'a str,
    state: &'a ServerState,
}

#[derive(Debug, thiserror::Error)]
pub enum SnapshotError {
    #[error("{path}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: not a curriculum snapshot")]
    Parse {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("{path}: damaged")]
    Corrupt {
        path: PathBuf,
        source: rfcl_core::checksum::ChecksumError,
    },
    #[error("{path}: snapshot format {found}, this server reads format {SNAPSHOT_FORMAT}")]
    Format { path: PathBuf, found: u32 },
    #[error("{path}: snapshot of run '{found}', but the config's run is '{expected}'")]
    OtherRun {
        path: PathBuf,
        found: String,
        expected: String,
    },
    #[error("both snapshot generations are damaged: {current}; and {previous}")]
    BothDamaged { current: String, previous: String },
}

impl SnapshotError {
    /// Damage to the file itself (as opposed to a snapshot of another run or format, which the
    /// generation before would share): the previous generation is tried instead.
    fn is_damage(&self) -> bool {
        matches!(self, Self::Parse { .. } | Self::Corrupt { .. })
    }
}

pub fn snapshot_path(run_dir: &Path) -> PathBuf {
    run_dir.join(SNAPSHOT_FILE)
}

/// Serialises and seals the state (call under the lock; write the bytes outside it).
pub fn encode(state: &ServerState, run_name: &str) -> Vec<u8> {
    rfcl_core::checksum::seal(
        serde_json::to_vec(&SnapshotFile {
            format: SNAPSHOT_FORMAT,
            run_name,
            checksum: rfcl_core::checksum::UNSEALED,
            state,
        })
        .expect("the server state always serialises"),
    )
}

/// Makes `bytes` (from [`encode`]) the run's snapshot: the current one, when intact, becomes the
/// previous generation first (a damaged one is dropped, keeping the intact previous one).
pub fn save(run_dir: &Path, bytes: &[u8]) -> Result<(), SnapshotError> {
    let current = snapshot_path(run_dir);
    match std::fs::read(&current) {
        Ok(old) if rfcl_core::checksum::verify(&old).is_ok() => {
            write(&run_dir.join(PREVIOUS_FILE), &old)?;
        }
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(source) => {
            return Err(SnapshotError::Io {
                path: current,
                source,
            })
        }
    }
    write(&current, bytes)
}

fn write(path: &Path, bytes: &[u8]) -> Result<(), SnapshotError> {
    rfcl_core::atomic::atomic_write(path, bytes).map_err(|source| SnapshotError::Io {
        path: path.into(),
        source,
    })
}

/// A snapshot read back, and what was skipped to get it.
pub struct Loaded {
    pub state: ServerState,
    pub path: PathBuf,
    /// The current snapshot's damage when this is the generation before it.
    pub skipped: Option<SnapshotError>,
}

/// The newest intact snapshot in `run_dir`, `None` when it holds none.
pub fn load_newest(run_dir: &Path, run_name: &str) -> Result<Option<Loaded>, SnapshotError> {
    let (current, previous) = (snapshot_path(run_dir), run_dir.join(PREVIOUS_FILE));
    let damage = match load(&current, run_name) {
        Ok(state) => {
            return Ok(Some(Loaded {
                state,
                path: current,
                skipped: None,
            }))
        }
        // A crash between the two writes of a save leaves only the previous generation.
        Err(SnapshotError::Io { source, .. }) if source.kind() == std::io::ErrorKind::NotFound => {
            None
        }
        Err(e) if e.is_damage() => Some(e),
        Err(e) => return Err(e),
    };
    match load(&previous, run_name) {
        Ok(state) => Ok(Some(Loaded {
            state,
            path: previous,
            skipped: damage,
        })),
        Err(SnapshotError::Io { source, .. }) if source.kind() == std::io::ErrorKind::NotFound => {
            damage.map_or(Ok(None), Err)
        }
        Err(e) => Err(match damage {
            Some(current) if e.is_damage() => SnapshotError::BothDamaged {
                current: rfcl_core::error::chain(&current),
                previous: rfcl_core::error::chain(&e),
            },
            _ => e,
        }),
    }
}

/// The snapshot in `path`, its checksum verified.
pub fn load(path: &Path, run_name: &str) -> Result<ServerState, SnapshotError> {
    let bytes = std::fs::read(path).map_err(|source| SnapshotError::Io {
        path: path.into(),
        source,
    })?;
    #[derive(Deserialize)]
    struct Header {
        format: u32,
        run_name: String,
    }
    let parse = |source| SnapshotError::Parse {
        path: path.into(),
        source,
    };
    let corrupt = |source| SnapshotError::Corrupt {
        path: path.into(),
        source,
    };
    // Checked before anything is read from the file: a flipped bit in its format or run name is
    // damage, not another format or run.
    let sealed = rfcl_core::checksum::verify(&bytes);
    if let Err(e @ rfcl_core::checksum::ChecksumError::Mismatch { .. }) = sealed {
        return Err(corrupt(e));
    }
    let header: Header = serde_json::from_slice(&bytes).map_err(parse)?;
    match header.format {
        SNAPSHOT_FORMAT => sealed.map_err(corrupt)?,
        FORMAT_V1 => {}
        found => {
            return Err(SnapshotError::Format {
                path: path.into(),
                found,
            })
        }
    }
    if header.run_name != run_name {
        return Err(SnapshotError::OtherRun {
            path: path.into(),
            found: header.run_name,
            expected: run_name.into(),
        });
    }
    #[derive(Deserialize)]
    struct Body {
        state: ServerState,
    }
    let body: Body = serde_json::from_slice(&bytes).map_err(parse)?;
    Ok(body.state)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Curriculum, DemoMeta};
    use rfcl_core::config::RunConfig;

    /// A state told apart by its episode count.
    fn state(episodes: u64) -> ServerState {
        let metas = [DemoMeta {
            success: vec![false, false, true],
            reset_seed: Some(0),
        }];
        let mut state =
            ServerState::new(Curriculum::new(&RunConfig::default(), &metas).unwrap(), 0.0);
        state.stats.episodes = episodes;
        state
    }

    fn flip_a_bit(path: &Path, at: usize) {
        let mut bytes = std::fs::read(path).unwrap();
        bytes[at] ^= 0x04;
        std::fs::write(path, bytes).unwrap();
    }

    fn newest(dir: &Path) -> (u64, PathBuf, Option<String>) {
        let loaded = load_newest(dir, "run").unwrap().expect("a snapshot");
        let skipped = loaded.skipped.map(|e| rfcl_core::error::chain(&e));
        (loaded.state.stats.episodes, loaded.path, skipped)
    }

    /// A run directory whose current snapshot holds 2 episodes and the previous one 1.
    fn two_generations() -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &encode(&state(1), "run")).unwrap();
        save(dir.path(), &encode(&state(2), "run")).unwrap();
        dir
    }

    #[test]
    fn a_save_keeps_the_generation_before_and_a_damaged_one_falls_back_to_it() {
        let empty = tempfile::tempdir().unwrap();
        assert!(load_newest(empty.path(), "run").unwrap().is_none());
        let len = encode(&state(2), "run").len();
        // A flipped bit anywhere, the format's digit and the run name included, is damage.
        for at in [10, 24, 200, len - 5] {
            let dir = two_generations();
            let (current, previous) = (snapshot_path(dir.path()), dir.path().join(PREVIOUS_FILE));
            assert_eq!(newest(dir.path()), (2, current.clone(), None));
            flip_a_bit(&current, at);
            // The generation before is resumed, naming what was skipped.
            let (episodes, path, skipped) = newest(dir.path());
            assert_eq!((episodes, &path), (1, &previous), "bit at {at}");
            let skipped = skipped.expect("the damage is named");
            assert!(
                skipped.contains("curriculum.snapshot.json: damaged")
                    || skipped.contains("curriculum.snapshot.json: not a curriculum snapshot"),
                "bit at {at}: {skipped}"
            );
            // The next save does not make the damaged file the fallback.
            save(dir.path(), &encode(&state(3), "run")).unwrap();
            assert_eq!(newest(dir.path()), (3, current, None));
            assert_eq!(load(&previous, "run").unwrap().stats.episodes, 1);
        }
    }

    #[test]
    fn both_generations_damaged_is_refused_naming_both() {
        let dir = two_generations();
        flip_a_bit(&snapshot_path(dir.path()), 100);
        flip_a_bit(&dir.path().join(PREVIOUS_FILE), 100);
        let e = load_newest(dir.path(), "run").err().expect("refused");
        let text = e.to_string();
        assert!(
            text.starts_with("both snapshot generations are damaged"),
            "{text}"
        );
        assert!(
            text.contains(SNAPSHOT_FILE) && text.contains(PREVIOUS_FILE),
            "{text}"
        );
        assert!(
            text.contains("the file was changed after it was written"),
            "{text}"
        );
    }

    #[test]
    fn a_crash_between_the_two_writes_of_a_save_resumes_the_previous_generation() {
        let dir = two_generations();
        std::fs::remove_file(snapshot_path(dir.path())).unwrap();
        assert_eq!(
            newest(dir.path()),
            (1, dir.path().join(PREVIOUS_FILE), None)
        );
    }

    #[test]
    fn another_run_is_refused_not_skipped_and_format_1_still_reads() {
        let dir = two_generations();
        let e = load_newest(dir.path(), "other").err().expect("refused");
        assert!(matches!(e, SnapshotError::OtherRun { .. }), "{e}");

        // A snapshot written before checksums: nothing to verify.
        let v1 = serde_json::json!({
            "format": 1,
            "run_name": "run",
            "state": serde_json::to_value(state(7)).unwrap(),
        });
        let path = dir.path().join("v1.json");
        std::fs::write(&path, serde_json::to_vec(&v1).unwrap()).unwrap();
        assert_eq!(load(&path, "run").unwrap().stats.episodes, 7);
    }
}
