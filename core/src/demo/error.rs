use std::path::PathBuf;

use thiserror::Error;

/// Why a demo file could not be read, written or used. Each message is one line naming the file
/// and what was expected.
#[derive(Debug, Error)]
pub enum DemoError {
    #[error("{}: demo file not found", path.display())]
    NotFound { path: PathBuf },

    #[error("{}: not an HDF5 file (expected a ManiSkill trajectory .h5 with traj_<id> groups)", path.display())]
    NotHdf5 { path: PathBuf },

    #[error("{}: no traj_<id> groups (expected a ManiSkill trajectory file)", path.display())]
    NoTrajectories { path: PathBuf },

    #[error("{}: traj_{episode_id} has no '{dataset}' dataset", path.display())]
    MissingDataset {
        path: PathBuf,
        episode_id: u64,
        dataset: String,
    },

    /// `what` has `rows` rows where `formula` (`T` or `T+1`) = `expected` follows from `actions`.
    #[error(
        "{}: traj_{episode_id}: {what} has {rows} rows but actions has {actions}: expected {formula} = {expected}",
        path.display()
    )]
    LengthMismatch {
        path: PathBuf,
        episode_id: u64,
        what: String,
        rows: usize,
        actions: usize,
        formula: &'static str,
        expected: usize,
    },

    /// Episodes disagree on a dim or on the env-state layout.
    #[error("{}: traj_{episode_id} has {what} {got} but traj_{first_episode_id} has {expected}", path.display())]
    InconsistentDims {
        path: PathBuf,
        episode_id: u64,
        what: &'static str,
        got: String,
        first_episode_id: u64,
        expected: String,
    },

    #[error(
        "{}: traj_{episode_id} is selected but no step has its success flag set: the reverse curriculum needs a success state at the end",
        path.display()
    )]
    NeverSucceeds { path: PathBuf, episode_id: u64 },

    #[error(
        "{}: {wanted} demos requested but only {successful} of {total} episodes succeeded",
        path.display()
    )]
    NotEnoughDemos {
        path: PathBuf,
        wanted: usize,
        successful: usize,
        total: usize,
    },

    #[error("{}: {what} dim {got} does not match {key} {expected}", path.display())]
    DimMismatch {
        path: PathBuf,
        what: &'static str,
        got: usize,
        key: &'static str,
        expected: usize,
    },

    /// Invalid JSON, or JSON of the wrong shape; serde's message carries line and column.
    #[error("{}: malformed JSON sidecar: {error}", path.display())]
    Sidecar {
        path: PathBuf,
        error: serde_json::Error,
    },

    /// Any other violation of the format: shapes, layouts, group names, sidecar entries.
    #[error("{}: {message}", path.display())]
    Format { path: PathBuf, message: String },

    /// The HDF5 library failed on a file that looked valid (`action` e.g. "read traj_3/obs").
    #[error("{}: cannot {action}: {message}", path.display())]
    Hdf5 {
        path: PathBuf,
        action: String,
        message: String,
    },

    #[error("{}: {error}", path.display())]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },

    #[error("{}: is a directory; expected an HDF5 demo file (a ManiSkill trajectory .h5)", path.display())]
    IsDirectory { path: PathBuf },

    /// NaN or infinity in a dataset: training on it diverges from the first update.
    #[error(
        "{}: traj_{episode_id}/{field} has {value} at step {step}, column {column}: demos must hold finite numbers",
        path.display()
    )]
    NonFinite {
        path: PathBuf,
        episode_id: u64,
        field: String,
        step: usize,
        column: usize,
        value: f32,
    },

    /// An MS3 actor's or articulation root's orientation that is not a unit quaternion: no
    /// simulator state has one, so the file is damaged or was written by hand.
    #[error(
        "{}: traj_{episode_id}/{field} has orientation (w, x, y, z) {quaternion:?} at step {step}, of norm {norm}: an orientation must be a unit quaternion (norm within {tolerance} of 1)",
        path.display()
    )]
    NotUnitQuaternion {
        path: PathBuf,
        episode_id: u64,
        field: String,
        step: usize,
        quaternion: [f32; 4],
        norm: f32,
        tolerance: f32,
    },
}

impl DemoError {
    pub(crate) fn format(path: &std::path::Path, message: impl Into<String>) -> Self {
        Self::Format {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }

    pub(crate) fn hdf5(
        path: &std::path::Path,
        action: impl Into<String>,
        err: hdf5::Error,
    ) -> Self {
        // HDF5's error stack descriptions may span lines; keep the message on one.
        let message = err
            .to_string()
            .split_whitespace()
            .collect::<Vec<_>>()
            .join(" ");
        Self::Hdf5 {
            path: path.to_path_buf(),
            action: action.into(),
            message,
        }
    }
}
