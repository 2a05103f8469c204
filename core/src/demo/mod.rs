//! Demonstration datasets in ManiSkill's trajectory format (spec 6.1): an HDF5 file with one group
//! `traj_<episode_id>` per demo, plus a JSON sidecar with the same base name.
//!
//! Per group:
//!
//! | key          | shape      | read as                                                     |
//! |--------------|------------|-------------------------------------------------------------|
//! | `actions`    | `[T, A]`   | `f32`                                                       |
//! | `obs`        | `[T+1, D]` | `f32` (float64 is converted); obs_mode "state" only          |
//! | `success`    | `[T]`      | `bool` (h5py's bool enum or any number, non-zero = true)    |
//! | `env_states` | `[T+1, ·]` | flattened to one `f32` row per step, see [`StateLayout`]    |
//!
//! A 1-D dataset counts as one column. `env_states` comes in three forms, all flattened the same
//! way (each row is the concatenation of the leaves, in the order below):
//!
//! * **MS2**: one flat dataset `env_states` `[T+1, S]` → one [`StateKind::Flat`] entry.
//! * **MS3**: groups `env_states/actors/<name>` `[T+1, 13]` (pos 3, quat 4, linear velocity 3,
//!   angular velocity 3) and `env_states/articulations/<name>` `[T+1, 13 + 2·dof]` (root pose 7,
//!   root velocity 6, qpos, qvel) → entries `actors/<name>` first, then `articulations/<name>`
//!   (spec 7.1).
//! * **Adroit / MetaWorld**: named datasets `env_states/<field>` `[T+1, k]` →
//!   [`StateKind::Field`] entries (spec 7.3, 7.4).
//!
//! Within a group, leaves follow the file's link order: creation order when the group tracks it
//! (files written by [`DemoSet::write`] do), name order otherwise (h5py's default). Adapters
//! rebuild their simulator's state dict by name from the layout, so this order is a convention,
//! not a contract with the simulator.
//!
//! The JSON sidecar gives `env_info` (`env_id`, `env_kwargs`, `max_episode_steps`) and
//! `episodes[]`; per demo we keep the reset seed and options, which must be applied before the
//! state (spec 2.4), and the episode's success flag. A missing sidecar is allowed: seeds are then
//! `None`, options `{}`, and [`DemoSet::summary`] says so.

mod error;
mod layout;
mod read;
mod sidecar;
mod summary;
mod write;

use std::path::{Path, PathBuf};

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

pub use error::DemoError;
pub use layout::{Quantity, StateEntry, StateKind, StateLayout, StatePart};

/// The arguments a demo's episode was reset with; applied before the demo's state (spec 2.4)
/// because geometry, goals and MetaWorld's random vector live outside the state vector.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ResetArgs {
    /// `reset_kwargs.seed`, else `episode_seed`; `None` without a sidecar.
    pub seed: Option<u64>,
    /// `reset_kwargs.options`, always a JSON object (`{}` when absent).
    pub options: serde_json::Value,
}

impl Default for ResetArgs {
    fn default() -> Self {
        Self {
            seed: None,
            options: serde_json::Value::Object(Default::default()),
        }
    }
}

/// Where a demo's per-step success flags came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SuccessSource {
    /// The trajectory's `success` dataset.
    Steps,
    /// The file has no `success` dataset: the sidecar's episode flag (`success` or
    /// `info.success`) labels the final step only.
    EpisodeFlag,
}

/// One demonstration: T actions, T + 1 observations and env states, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Demo {
    pub episode_id: u64,
    pub obs_dim: usize,
    pub action_dim: usize,
    pub state_dim: usize,
    /// `[(T+1) × obs_dim]`
    pub obs: Vec<f32>,
    /// `[T × action_dim]`
    pub actions: Vec<f32>,
    /// `[T]`: `success[t]` is the success flag after action t (the offline reward, spec 6.2).
    pub success: Vec<bool>,
    /// `[(T+1) × state_dim]`, laid out by the set's [`StateLayout`].
    pub env_states: Vec<f32>,
    /// The episode's outcome, used to skip failed episodes (spec 6.1): the sidecar's flag when it
    /// has one, else the last step's flag.
    pub succeeded: bool,
    pub success_source: SuccessSource,
    pub reset: ResetArgs,
}

impl Demo {
    /// T, the number of actions.
    pub fn len(&self) -> usize {
        self.success.len()
    }

    pub fn is_empty(&self) -> bool {
        self.success.is_empty()
    }

    /// T + 1, the number of observations and env states (the spec's S_i before truncation, 2.1).
    pub fn num_states(&self) -> usize {
        self.len() + 1
    }

    /// Observation `t`, for `t` in `0..=T`.
    pub fn obs_row(&self, t: usize) -> &[f32] {
        &self.obs[t * self.obs_dim..(t + 1) * self.obs_dim]
    }

    /// Action `t`, for `t` in `0..T`.
    pub fn action_row(&self, t: usize) -> &[f32] {
        &self.actions[t * self.action_dim..(t + 1) * self.action_dim]
    }

    /// Env state `s`, for `s` in `0..=T`.
    pub fn state_row(&self, s: usize) -> &[f32] {
        &self.env_states[s * self.state_dim..(s + 1) * self.state_dim]
    }

    /// The first step whose success flag is set.
    pub fn first_success(&self) -> Option<usize> {
        self.success.iter().position(|&s| s)
    }

    /// The number of success-flagged steps (n_succ of spec 2.1's light truncation).
    pub fn success_count(&self) -> usize {
        self.success.iter().filter(|&&s| s).count()
    }
}

/// A demo file, loaded whole, or a selection of its demos.
#[derive(Debug, Clone, PartialEq)]
pub struct DemoSet {
    /// The HDF5 file.
    pub path: PathBuf,
    /// The JSON sidecar it was read with, `None` when the file had none.
    pub sidecar: Option<PathBuf>,
    /// `env_info.env_id`.
    pub env_id: Option<String>,
    /// The sidecar's whole `env_info` object (`Null` without a sidecar).
    pub env_info: serde_json::Value,
    /// `env_info.env_kwargs.control_mode`, else the first `control_mode` of `episodes[]`.
    pub control_mode: Option<String>,
    pub obs_dim: usize,
    pub action_dim: usize,
    pub state_dim: usize,
    pub state_layout: StateLayout,
    /// In file order (ascending episode id) after [`load`](Self::load), in selection order after
    /// [`select`](Self::select).
    pub demos: Vec<Demo>,
}

impl DemoSet {
    /// Reads a trajectory file and its JSON sidecar (`path` with the extension `.json`), if any.
    pub fn load(path: &Path) -> Result<DemoSet, DemoError> {
        read::load(path)
    }

    /// Demo selection (spec 6.1): shuffle the episodes with `seed` if `shuffle`, skip failed
    /// episodes, take the first `num_demos`. Fails when fewer episodes succeeded, or when a chosen
    /// demo has no success-flagged step (the reverse curriculum starts from a success state).
    ///
    /// The shuffle is a ChaCha8 Fisher–Yates shuffle: deterministic per seed, but not NumPy's
    /// order, so the reference picks different demos for the same seed.
    pub fn select(&self, num_demos: usize, shuffle: bool, seed: u64) -> Result<DemoSet, DemoError> {
        let mut order: Vec<&Demo> = self.demos.iter().collect();
        if shuffle {
            order.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
        }
        let chosen: Vec<Demo> = order
            .into_iter()
            .filter(|d| d.succeeded)
            .take(num_demos)
            .cloned()
            .collect();
        if chosen.len() < num_demos {
            return Err(DemoError::NotEnoughDemos {
                path: self.path.clone(),
                wanted: num_demos,
                successful: chosen.len(),
                total: self.demos.len(),
            });
        }
        if let Some(demo) = chosen.iter().find(|d| d.first_success().is_none()) {
            return Err(DemoError::NeverSucceeds {
                path: self.path.clone(),
                episode_id: demo.episode_id,
            });
        }
        Ok(DemoSet {
            demos: chosen,
            ..self.without_demos()
        })
    }

    /// Checks the demo dims against the configured env (`env.obs_dim`, `env.action_dim`).
    pub fn check_dims(
        &self,
        obs_dim: Option<usize>,
        action_dim: Option<usize>,
    ) -> Result<(), DemoError> {
        let checks = [
            ("obs", "env.obs_dim", self.obs_dim, obs_dim),
            ("action", "env.action_dim", self.action_dim, action_dim),
        ];
        for (what, key, got, expected) in checks {
            if let Some(expected) = expected.filter(|&e| e != got) {
                return Err(DemoError::DimMismatch {
                    path: self.path.clone(),
                    what,
                    got,
                    key,
                    expected,
                });
            }
        }
        Ok(())
    }

    /// Writes the set in ManiSkill's format: the MS3 nested `env_states` groups (or named fields)
    /// unless the layout is flat, per-step `success`, and the JSON sidecar next to `path`.
    /// Used by demo generators and converters, and by tests to exercise every reader path.
    pub fn write(&self, path: &Path) -> Result<(), DemoError> {
        write::write(self, path)
    }

    /// A human-readable report for `rfcl demos inspect`: episodes, lengths, dims, success flags,
    /// the state layout and the reset seeds.
    pub fn summary(&self) -> String {
        summary::summary(self)
    }

    /// The JSON sidecar path that belongs to an HDF5 path: same base name, extension `.json`.
    pub fn sidecar_path(path: &Path) -> PathBuf {
        path.with_extension("json")
    }

    fn without_demos(&self) -> DemoSet {
        DemoSet {
            path: self.path.clone(),
            sidecar: self.sidecar.clone(),
            env_id: self.env_id.clone(),
            env_info: self.env_info.clone(),
            control_mode: self.control_mode.clone(),
            obs_dim: self.obs_dim,
            action_dim: self.action_dim,
            state_dim: self.state_dim,
            state_layout: self.state_layout.clone(),
            demos: Vec::new(),
        }
    }
}
