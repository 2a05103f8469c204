//! Small synthetic demo files for the services' tests.
//!
//! Each demo's env states encode where they come from: state `s` of demo `i` is
//! `[i, s, 0.5, -0.5]` (so a lease's `env_state` names its demo and start index), and demo `i`
//! resets with seed `100 + i`. Observations and actions come from the caller's functions, so each
//! crate keeps the values its assertions were written against.
use std::path::{Path, PathBuf};

use rfcl_core::demo::{Demo, DemoSet, ResetArgs, StateLayout, SuccessSource};

/// The env-state width of synthetic demos: `[demo, step, 0.5, -0.5]`.
pub const STATE_DIM: usize = 4;

/// A synthetic PointMaze-v0 demo set: `demos` demos of `steps` actions each, succeeding on their
/// last `success_steps` steps.
#[derive(Clone, Copy, Debug)]
pub struct SyntheticDemos {
    pub demos: usize,
    /// Actions per demo (a demo has `steps + 1` observations and states).
    pub steps: usize,
    pub obs_dim: usize,
    pub action_dim: usize,
    /// The last this many steps carry the success flag.
    pub success_steps: usize,
    /// `max_episode_steps` in the file's env info.
    pub max_episode_steps: u32,
    /// Value `k` of demo `demo`'s flat observations (`(steps + 1) * obs_dim` of them).
    pub obs: fn(demo: usize, k: usize) -> f32,
    /// Value `k` of demo `demo`'s flat actions (`steps * action_dim` of them).
    pub action: fn(demo: usize, k: usize) -> f32,
}

impl SyntheticDemos {
    /// The demo set, to be written at `path`.
    pub fn demo_set(&self, path: &Path) -> DemoSet {
        let t = self.steps;
        let demos = (0..self.demos)
            .map(|i| Demo {
                episode_id: i as u64,
                obs_dim: self.obs_dim,
                action_dim: self.action_dim,
                state_dim: STATE_DIM,
                obs: (0..(t + 1) * self.obs_dim)
                    .map(|k| (self.obs)(i, k))
                    .collect(),
                actions: (0..t * self.action_dim)
                    .map(|k| (self.action)(i, k))
                    .collect(),
                success: (0..t).map(|s| s + self.success_steps >= t).collect(),
                env_states: (0..=t)
                    .flat_map(|s| [i as f32, s as f32, 0.5, -0.5])
                    .collect(),
                succeeded: true,
                success_source: SuccessSource::Steps,
                reset: ResetArgs {
                    seed: Some(100 + i as u64),
                    options: serde_json::json!({}),
                },
            })
            .collect();
        DemoSet {
            path: path.to_path_buf(),
            sidecar: None,
            env_id: Some("PointMaze-v0".into()),
            env_info: serde_json::json!({
                "env_id": "PointMaze-v0",
                "env_kwargs": {},
                "max_episode_steps": self.max_episode_steps,
            }),
            control_mode: None,
            obs_dim: self.obs_dim,
            action_dim: self.action_dim,
            state_dim: STATE_DIM,
            state_layout: StateLayout::flat(STATE_DIM),
            demos,
        }
    }

    /// Writes the set to `dir/demos.h5` under the HDF5 fork lock; returns the path.
    pub fn write(&self, dir: &Path) -> PathBuf {
        let path = dir.join("demos.h5");
        write_demo_set(&self.demo_set(&path), &path);
        path
    }
}

/// Writes `set` to `path` under the HDF5 fork lock ([`crate::hdf5`]), panicking on failure.
pub fn write_demo_set(set: &DemoSet, path: &Path) {
    let _guard = crate::hdf5::fork_guard();
    set.write(path)
        .unwrap_or_else(|e| panic!("writing the test demos to {}: {e}", path.display()));
}

/// Writes a D4RL-format Adroit Door file at `path` with tests/adroit_d4rl.py: `open` episodes
/// that succeed, `closed` that do not, `steps` steps each.
pub fn write_d4rl_door(path: &Path, open: u32, closed: u32, steps: u32) {
    crate::child::succeed(
        std::process::Command::new(rfcl_core::python::python_program())
            .arg(crate::binaries::workspace_root().join("tests/adroit_d4rl.py"))
            .arg(path)
            .args([open, closed, steps].map(|n| n.to_string())),
    );
}

/// A copy, in `dir` as `damaged.h5`, of the committed fuzzing reproducer that crashes libhdf5
/// itself when read (fuzz/artifacts/demo_hdf5/upstream/): every reader of user demo files must
/// name such a file instead of dying of a segmentation fault.
pub fn hdf5_crash_reproducer(dir: &Path) -> PathBuf {
    let reproducers =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/artifacts/demo_hdf5/upstream");
    let crash = std::fs::read_dir(&reproducers)
        .unwrap_or_else(|e| panic!("{}: {e}", reproducers.display()))
        .flatten()
        .find(|e| e.file_name().to_string_lossy().starts_with("crash-"))
        .expect("a committed libhdf5 crash reproducer");
    let file = dir.join("damaged.h5");
    std::fs::copy(crash.path(), &file).expect("copying the reproducer");
    file
}
