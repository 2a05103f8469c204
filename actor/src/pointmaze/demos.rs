//! PointMaze demonstrations: a breadth-first path over maze cells from the start cell to the goal,
//! followed by a proportional controller through the cell centres.
//!
//! The corridors are one cell wide and the collision margin leaves a band of ±0.35 around each
//! corridor's centre line. The controller aims at the next cell centre and moves on to the following
//! one within [`WAYPOINT_TOLERANCE`] of it, so the point never leaves that band: demos are free of
//! collisions. At the goal it keeps stepping until it has spent [`SUCCESS_STEPS`] steps in success,
//! so every demo ends in a success state, where the reverse curriculum starts (spec 2.1).

use std::collections::HashSet;
use std::path::PathBuf;

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rfcl_core::demo::{Demo, DemoSet, ResetArgs, SuccessSource};
use serde_json::json;

use super::{
    cell_centre, maze, seed_cell, state_layout, Cell, PointMaze, ACTION_DIM, DT, ENV_ID, HORIZON,
    MAX_SPEED, OBS_DIM, STATE_DIM, SUBSTEPS,
};
use crate::env::{Env, EnvError};

/// Consecutive success steps that end a demo.
pub const SUCCESS_STEPS: usize = 10;
/// Distance to a waypoint at which the controller aims at the next one.
pub const WAYPOINT_TOLERANCE: f32 = 0.1;
/// Distance covered by one full action: the controller's gain is its inverse.
const STEP_REACH: f32 = MAX_SPEED * DT * SUBSTEPS as f32;

/// One demonstration, as plain row-major arrays (the shapes of ManiSkill's trajectory format,
/// spec 6.1). `T` = [`PointMazeDemo::len`] actions. [`demo_set`] turns demos into a
/// [`DemoSet`] that can be written to disk.
#[derive(Debug, Clone, PartialEq)]
pub struct PointMazeDemo {
    /// The seed of the reset the demo started from (its `reset_kwargs`, spec 2.4 step 3).
    pub reset_seed: u64,
    /// The start cell, [`seed_cell`]`(reset_seed)`.
    pub start_cell: Cell,
    /// Observations, `[T + 1, OBS_DIM]`.
    pub obs: Vec<f32>,
    /// Actions, `[T, ACTION_DIM]`.
    pub actions: Vec<f32>,
    /// Success flag of the state after each action, `[T]`.
    pub success: Vec<bool>,
    /// Env states, `[T + 1, STATE_DIM]` (layout in the module docs of [`super`]).
    pub env_states: Vec<f32>,
}

impl PointMazeDemo {
    /// Number of actions T.
    pub fn len(&self) -> usize {
        self.success.len()
    }

    /// Whether the demo has no actions.
    pub fn is_empty(&self) -> bool {
        self.success.is_empty()
    }

    /// Observation `t` in `0..=T`.
    pub fn obs_at(&self, t: usize) -> &[f32] {
        &self.obs[t * OBS_DIM..(t + 1) * OBS_DIM]
    }

    /// Action `t` in `0..T`.
    pub fn action_at(&self, t: usize) -> &[f32] {
        &self.actions[t * ACTION_DIM..(t + 1) * ACTION_DIM]
    }

    /// Env state `t` in `0..=T`.
    pub fn state_at(&self, t: usize) -> &[f32] {
        &self.env_states[t * STATE_DIM..(t + 1) * STATE_DIM]
    }

    /// This demo as episode `episode_id` of a demo set, resetting with `{seed: reset_seed,
    /// options: {}}`.
    pub fn into_demo(self, episode_id: u64) -> Demo {
        Demo {
            episode_id,
            obs_dim: OBS_DIM,
            action_dim: ACTION_DIM,
            state_dim: STATE_DIM,
            succeeded: self.success.last() == Some(&true),
            obs: self.obs,
            actions: self.actions,
            success: self.success,
            env_states: self.env_states,
            success_source: SuccessSource::Steps,
            reset: ResetArgs {
                seed: Some(self.reset_seed),
                options: json!({}),
            },
        }
    }
}

/// `demos` as a demo set (episode ids `0..`) to be written to `path` with [`DemoSet::write`] in
/// ManiSkill's trajectory format (spec 6.1); `env_info` names [`ENV_ID`] and the horizon.
pub fn demo_set(demos: Vec<PointMazeDemo>, path: impl Into<PathBuf>) -> DemoSet {
    DemoSet {
        path: path.into(),
        sidecar: None,
        env_id: Some(ENV_ID.to_owned()),
        env_info: json!({ "env_id": ENV_ID, "max_episode_steps": HORIZON, "env_kwargs": {} }),
        control_mode: None,
        obs_dim: OBS_DIM,
        action_dim: ACTION_DIM,
        state_dim: STATE_DIM,
        state_layout: state_layout(),
        demos: (0..).zip(demos).map(|(id, d)| d.into_demo(id)).collect(),
    }
}

/// Why a demo could not be planned.
#[derive(Debug, thiserror::Error)]
pub enum PlanError {
    /// The start cell has no corridor path to the goal.
    #[error("start cell {0:?} has no path to the goal")]
    NoPath(Cell),
    /// The controller did not finish within the horizon.
    #[error("the demo from cell {cell:?} did not finish within {HORIZON} steps")]
    Horizon { cell: Cell },
    /// The env refused a call.
    #[error(transparent)]
    Env(#[from] EnvError),
}

/// Plans one demo from a reset with `reset_seed`: start cell `seed_cell(reset_seed)`.
pub fn plan_demo(reset_seed: u64) -> Result<PointMazeDemo, PlanError> {
    let start_cell = seed_cell(reset_seed);
    let path = maze()
        .path_to_goal(start_cell)
        .ok_or(PlanError::NoPath(start_cell))?;
    let waypoints: Vec<[f32; 2]> = path.into_iter().map(cell_centre).collect();

    let mut env = PointMaze::new(reset_seed);
    let first_obs = env.reset_to_seed(Some(reset_seed), &serde_json::Value::Null)?;
    let mut demo = PointMazeDemo {
        reset_seed,
        start_cell,
        obs: first_obs,
        actions: Vec::new(),
        success: Vec::new(),
        env_states: env.get_state(),
    };
    let mut next = 0;
    let mut success_run = 0;
    while success_run < SUCCESS_STEPS {
        if demo.len() == HORIZON {
            return Err(PlanError::Horizon { cell: start_cell });
        }
        let pos = env.position();
        let reached = |w: [f32; 2]| (w[0] - pos[0]).hypot(w[1] - pos[1]) < WAYPOINT_TOLERANCE;
        while next + 1 < waypoints.len() && reached(waypoints[next]) {
            next += 1;
        }
        let target = waypoints[next];
        let action = [0, 1].map(|a| ((target[a] - pos[a]) / STEP_REACH).clamp(-1.0, 1.0));
        let outcome = env.step(&action)?;
        demo.actions.extend(action);
        demo.success.push(outcome.success);
        demo.obs.extend(outcome.obs);
        demo.env_states.extend(env.get_state());
        success_run = if outcome.success { success_run + 1 } else { 0 };
    }
    Ok(demo)
}

/// `n` demos from distinct start cells while `n` ≤ 34, chosen to cover the maze.
///
/// The start cells are taken greedily: each next one is the cell whose path to the goal passes the
/// most cells that no earlier demo's path passes, ties broken by an order shuffled by `seed`. Three
/// demos (one per dead end) pass every start cell; from then on the order is the shuffled one. Demo
/// `k` resets with seed `order[k % 34] + 34 · (k / 34)`: a demo's seed maps to its start cell
/// (spec 7.5), and demos beyond the 34th revisit cells with other jitters.
///
/// # Panics
/// If a demo cannot be planned. The maze is fixed and the tests plan every start cell, so this does
/// not happen.
pub fn generate_demos(n: usize, seed: u64) -> Vec<PointMazeDemo> {
    let order = covering_order(seed);
    let cells = order.len() as u64;
    (0..n as u64)
        .map(|k| {
            let reset_seed = order[(k % cells) as usize] + cells * (k / cells);
            plan_demo(reset_seed).expect("every start cell of the fixed maze has a demo")
        })
        .collect()
}

/// Every start-cell index once, in the greedy path-covering order of [`generate_demos`].
fn covering_order(seed: u64) -> Vec<u64> {
    let maze = maze();
    let paths: Vec<Vec<Cell>> = maze
        .start_cells()
        .iter()
        .map(|&cell| {
            maze.path_to_goal(cell)
                .expect("every start cell reaches the goal")
        })
        .collect();
    let mut remaining: Vec<u64> = (0..paths.len() as u64).collect();
    remaining.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let mut covered = HashSet::new();
    let mut order = Vec::with_capacity(remaining.len());
    while !remaining.is_empty() {
        let new_cells = |i: u64| {
            paths[i as usize]
                .iter()
                .filter(|c| !covered.contains(*c))
                .count()
        };
        // The first of the best in shuffled order: `max_by_key` would keep the last.
        let best = (0..remaining.len())
            .rev()
            .max_by_key(|&j| new_cells(remaining[j]))
            .expect("remaining is not empty");
        let index = remaining.remove(best);
        covered.extend(paths[index as usize].iter().copied());
        order.push(index);
    }
    order
}
