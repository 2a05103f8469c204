//! Curriculum snapshots: the whole [`ServerState`] (curricula, random stream, leases, counters) in a
//! versioned JSON file, replaced atomically. A server restarted with `--resume` from a snapshot
//! hands out exactly what an uninterrupted one would have after that snapshot.
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::state::ServerState;

/// Bumped whenever the snapshot's shape changes; older files are refused with a clear error.
pub const SNAPSHOT_FORMAT: u32 = 1;
pub const SNAPSHOT_FILE: &str = "curriculum.snapshot.json";

#[derive(Serialize, Deserialize)]
struct SnapshotFile<S> {
    format: u32,
    run_name: String,
    state: S,
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
    #[error("{path}: snapshot format {found}, this server reads format {SNAPSHOT_FORMAT}")]
    Format { path: PathBuf, found: u32 },
    #[error("{path}: snapshot of run '{found}', but the config's run is '{expected}'")]
    OtherRun {
        path: PathBuf,
        found: String,
        expected: String,
    },
}

pub fn snapshot_path(run_dir: &Path) -> PathBuf {
    run_dir.join(SNAPSHOT_FILE)
}

/// Serialises the state (call under the lock; write the bytes outside it).
pub fn encode(state: &ServerState, run_name: &str) -> Vec<u8> {
    serde_json::to_vec(&SnapshotFile {
        format: SNAPSHOT_FORMAT,
        run_name: run_name.to_string(),
        state,
    })
    .expect("the server state always serialises")
}

pub fn write(path: &Path, bytes: &[u8]) -> Result<(), SnapshotError> {
    rfcl_core::atomic::atomic_write(path, bytes).map_err(|source| SnapshotError::Io {
        path: path.into(),
        source,
    })
}

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
    let header: Header = serde_json::from_slice(&bytes).map_err(|source| SnapshotError::Parse {
        path: path.into(),
        source,
    })?;
    if header.format != SNAPSHOT_FORMAT {
        return Err(SnapshotError::Format {
            path: path.into(),
            found: header.format,
        });
    }
    if header.run_name != run_name {
        return Err(SnapshotError::OtherRun {
            path: path.into(),
            found: header.run_name,
            expected: run_name.into(),
        });
    }
    let file: SnapshotFile<ServerState> =
        serde_json::from_slice(&bytes).map_err(|source| SnapshotError::Parse {
            path: path.into(),
            source,
        })?;
    Ok(file.state)
}
