//! PointMaze (spec 7.5): a point mass in a fixed 12×12 maze, the toy task of the paper's heatmap
//! figure, simulated natively in Rust. Deterministic given its seeds.
//!
//! * **Layout**: [`maze::MAP`]; cell `(row, col)` is centred on `x = col`, `y = row`. The goal is
//!   the centre of the goal cell. There are 34 start cells (spec 7.5: `num_seeds` 34).
//! * **Observation** (7): `x, y, vx, vy, goal_x, goal_y, collided_once` (the flag is 0 or 1).
//! * **Action** (2): a velocity command in `[-1, 1]²` (components outside are clipped).
//! * **Dynamics**: the velocity is `action × MAX_SPEED`, held for [`SUBSTEPS`] substeps of
//!   [`DT`], then zeroed: each action starts from rest, with no momentum. A substep moves the
//!   point along x and then along y; walls block it (a wall is a unit square inflated by the point's
//!   radius [`POINT_RADIUS`]; a blocked axis stops at the face and its velocity drops to 0). One
//!   step moves at most `MAX_SPEED × SUBSTEPS × DT` = 0.2 cells per axis. `vx, vy` report the
//!   velocity of the last substep; the dynamics never read them.
//! * **Collision**: after each substep, being within [`COLLISION_MARGIN`] of a hazard wall cell's
//!   centre (`X` in [`rfcl_core::maze::MAP`], the spec's "2" cells) in both x and y. The
//!   collided-once flag then stays set until the next reset. Touching a hazard implies a collision
//!   since `0.5 + POINT_RADIUS < COLLISION_MARGIN`; other walls only block.
//! * **Success**: distance to the goal ≤ [`GOAL_RADIUS`] and no collision so far, judged on the
//!   state after the action. Episodes never end on success (spec 5.6); the horizon is [`HORIZON`].
//! * **Reset with a seed**: start cell [`Maze::seed_cell`] (seed mod 34), plus a uniform jitter of
//!   at most [`START_JITTER`] per axis drawn from `ChaCha8Rng::seed_from_u64(seed)`, which also
//!   becomes the env's RNG.
//! * **Reset without a seed**: a uniform start cell from the env's RNG; cells at most
//!   [`NEAR_GOAL_DISTANCE`] cells from the goal along the corridors are redrawn with probability
//!   [`NEAR_GOAL_RESAMPLE_P`]; then the same jitter.
//! * **State** (5): `qpos (x, y)`, `qvel (vx, vy)`, `collided (0 or 1)`, three
//!   [`StateKind::Field`] entries: everything a step reads, so a restored state steps exactly like
//!   the original.
//!
//! [`demos`] plans collision-free demonstrations through the maze.

pub mod demos;
pub mod draw;
pub use rfcl_core::maze;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::env::{Env, EnvError, Frame, StateKind, StateLayout, StepOutcome};
pub use maze::{cell_at, cell_centre, maze, Cell, Maze, MAP};

/// The env id of PointMaze in run configs and demo files.
pub const ENV_ID: &str = "PointMaze-v0";
/// Observation length: `x, y, vx, vy, goal_x, goal_y, collided_once`.
pub const OBS_DIM: usize = 7;
/// Action length: a velocity command per axis.
pub const ACTION_DIM: usize = 2;
/// State length: `qpos (2), qvel (2), collided (1)`.
pub const STATE_DIM: usize = 5;
/// Episode horizon (spec 7.5, 8.3).
pub const HORIZON: usize = 300;
/// Physics substeps per action (spec 7.5).
pub const SUBSTEPS: usize = 10;
/// Substep duration.
pub const DT: f32 = 0.01;
/// Speed of a full action, in cells per unit time.
pub const MAX_SPEED: f32 = 2.0;
/// Radius of the point; walls block it at `0.5 + POINT_RADIUS` from their centre on both axes.
pub const POINT_RADIUS: f32 = 0.1;
/// A collision is being within this distance of a hazard wall cell's centre in both x and y (spec 7.5).
pub const COLLISION_MARGIN: f32 = 0.65;
/// Success is being within this distance of the goal, without a collision so far (spec 7.5).
pub const GOAL_RADIUS: f32 = 0.45;
/// Largest start offset from the start cell's centre, per axis.
pub const START_JITTER: f32 = 0.25;
/// Start cells at most this many cells from the goal (along the corridors) count as near the goal
/// for unseeded resets.
pub const NEAR_GOAL_DISTANCE: usize = 5;
/// Probability that an unseeded reset redraws a start cell near the goal (spec 7.5).
pub const NEAR_GOAL_RESAMPLE_P: f64 = 0.95;

/// Half-size of a wall's blocking square: the wall's half-width plus the point's radius.
const BLOCK_HALF: f32 = 0.5 + POINT_RADIUS;

/// The start cells in seed order, for heatmaps of success per start cell: seed `s` starts in
/// `start_cells()[s % 34]`.
pub fn start_cells() -> Vec<Cell> {
    maze().start_cells().to_vec()
}

/// The start cell of a seeded reset (the level of the forward curriculum, spec 3.1).
pub fn seed_cell(seed: u64) -> Cell {
    maze().seed_cell(seed)
}

/// The state layout: `qpos (x, y)`, `qvel (vx, vy)`, `collided (0 or 1)`, all
/// [`StateKind::Field`] entries.
pub fn state_layout() -> StateLayout {
    let fields = [("qpos", 2), ("qvel", 2), ("collided", 1)];
    StateLayout::from_parts(fields.map(|(name, len)| (name.to_owned(), StateKind::Field, len)))
}

/// The goal position `[x, y]`.
pub fn goal_position() -> [f32; 2] {
    cell_centre(maze().goal_cell())
}

/// Whether position `[x, y]` collides: within [`COLLISION_MARGIN`] of a hazard wall cell's centre
/// in both x and y. Positions outside the grid collide.
pub fn collides(pos: [f32; 2]) -> bool {
    cell_at(pos).is_none_or(|cell| colliding_wall(cell, pos).is_some())
}

/// The hazard wall cell that position `pos`, inside `cell`, collides with, if any.
fn colliding_wall(cell: Cell, pos: [f32; 2]) -> Option<Cell> {
    maze().hazards_around(cell).find(|&wall| {
        let centre = cell_centre(wall);
        (0..2).all(|a| {
            centre[a] - COLLISION_MARGIN <= pos[a] && pos[a] <= centre[a] + COLLISION_MARGIN
        })
    })
}

/// Whether coordinate `v` lies strictly between the blocking faces `centre ± BLOCK_HALF` of a wall,
/// computed exactly as the faces a blocked point is put on, so that a point on a face is outside.
fn inside_face(centre: f32, v: f32) -> bool {
    centre - BLOCK_HALF < v && v < centre + BLOCK_HALF
}

/// Whether position `[x, y]` is a success position for a run without collisions.
pub fn at_goal(pos: [f32; 2]) -> bool {
    let goal = goal_position();
    (pos[0] - goal[0]).hypot(pos[1] - goal[1]) <= GOAL_RADIUS
}

/// The PointMaze env (spec 7.5). See the module docs for the rules.
#[derive(Debug, Clone)]
pub struct PointMaze {
    pos: [f32; 2],
    vel: [f32; 2],
    collided: bool,
    rng: ChaCha8Rng,
    layout: StateLayout,
    /// Where the point was at each step since the reset, for [`Env::render`] (at most
    /// [`TRAIL_MAX`]).
    trail: Vec<[f32; 2]>,
}

/// Positions a render's trail keeps: more than an episode's 300 steps.
const TRAIL_MAX: usize = 4096;

impl PointMaze {
    /// An env whose RNG starts from `seed`, already reset without a seed from that RNG.
    pub fn new(seed: u64) -> Self {
        let mut env = Self {
            pos: [0.0; 2],
            vel: [0.0; 2],
            collided: false,
            rng: ChaCha8Rng::seed_from_u64(seed),
            layout: state_layout(),
            trail: Vec::new(),
        };
        let cell = env.sample_cell();
        env.place(cell);
        env
    }

    /// The point's position `[x, y]`.
    pub fn position(&self) -> [f32; 2] {
        self.pos
    }

    /// Whether the point has collided with a wall since the last reset.
    pub fn collided(&self) -> bool {
        self.collided
    }

    /// Whether the current state is a success state.
    pub fn is_success(&self) -> bool {
        !self.collided && at_goal(self.pos)
    }

    /// The cell the point is in.
    pub fn cell(&self) -> Cell {
        cell_at(self.pos).expect("walls keep the point inside the grid")
    }

    /// The current observation.
    pub fn obs(&self) -> Vec<f32> {
        let [x, y] = self.pos;
        let [vx, vy] = self.vel;
        let [gx, gy] = goal_position();
        vec![x, y, vx, vy, gx, gy, f32::from(u8::from(self.collided))]
    }

    /// A start cell for an unseeded reset: uniform, with cells near the goal redrawn with
    /// probability [`NEAR_GOAL_RESAMPLE_P`] (spec 7.5).
    fn sample_cell(&mut self) -> Cell {
        let cells = maze().start_cells();
        loop {
            let cell = cells[self.rng.random_range(0..cells.len())];
            let near = maze()
                .distance_to_goal(cell)
                .is_some_and(|d| d <= NEAR_GOAL_DISTANCE);
            if !(near && self.rng.random_bool(NEAR_GOAL_RESAMPLE_P)) {
                return cell;
            }
        }
    }

    /// Puts the point at rest at a jittered position in `cell` and clears the collision flag.
    fn place(&mut self, cell: Cell) {
        let [cx, cy] = cell_centre(cell);
        let jx = self.rng.random_range(-START_JITTER..=START_JITTER);
        let jy = self.rng.random_range(-START_JITTER..=START_JITTER);
        self.pos = [cx + jx, cy + jy];
        self.vel = [0.0; 2];
        self.collided = false;
        self.trail.clear();
    }

    /// Moves the point by one substep along `axis`, stopping at the face of any wall it would enter.
    fn move_axis(&mut self, axis: usize, vel: &mut [f32; 2]) {
        let forward = vel[axis] > 0.0;
        let mut next = self.pos;
        next[axis] += vel[axis] * DT;
        let other = 1 - axis;
        for wall in maze().walls_around(self.cell()) {
            let centre = cell_centre(wall);
            if inside_face(centre[other], next[other]) && inside_face(centre[axis], next[axis]) {
                next[axis] = if forward {
                    centre[axis] - BLOCK_HALF
                } else {
                    centre[axis] + BLOCK_HALF
                };
                vel[axis] = 0.0;
            }
        }
        self.pos = next;
    }

    /// Checks a state vector and decodes it into `(pos, vel, collided)`.
    fn decode_state(&self, state: &[f32]) -> Result<([f32; 2], [f32; 2], bool), EnvError> {
        if state.len() != STATE_DIM {
            return Err(EnvError::StateLen {
                expected: STATE_DIM,
                got: state.len(),
            });
        }
        let invalid = |field: &str, reason: String| EnvError::InvalidState {
            field: field.to_owned(),
            reason,
        };
        for entry in self.layout.entries() {
            if let Some(v) = state[entry.range()].iter().find(|v| !v.is_finite()) {
                return Err(invalid(&entry.name, format!("{v} is not a finite number")));
            }
        }
        let pos = [state[0], state[1]];
        let vel = [state[2], state[3]];
        let collided = match state[4] {
            0.0 => false,
            1.0 => true,
            other => return Err(invalid("collided", format!("{other} is neither 0 nor 1"))),
        };
        let Some(cell) = cell_at(pos) else {
            return Err(invalid("qpos", format!("{pos:?} lies outside the maze")));
        };
        let inside = maze().walls_around(cell).find(|&wall| {
            let centre = cell_centre(wall);
            (0..2).all(|a| inside_face(centre[a], pos[a]))
        });
        if let Some(wall) = inside {
            return Err(invalid(
                "qpos",
                format!("{pos:?} lies inside wall cell {wall:?}"),
            ));
        }
        if let (false, Some(wall)) = (collided, colliding_wall(cell, pos)) {
            let reason = format!(
                "0 at {pos:?}, within {COLLISION_MARGIN} of hazard wall cell {wall:?}: a collision"
            );
            return Err(invalid("collided", reason));
        }
        Ok((pos, vel, collided))
    }
}

/// PointMaze takes no reset options: `null` or `{}`.
fn check_options(options: &serde_json::Value) -> Result<(), EnvError> {
    match options {
        serde_json::Value::Null => Ok(()),
        serde_json::Value::Object(map) if map.is_empty() => Ok(()),
        other => Err(EnvError::InvalidOptions {
            reason: format!("PointMaze takes no reset options, got {other}"),
        }),
    }
}

/// Checks an action's length and values and clips it into `[-1, 1]²`.
fn check_action(action: &[f32]) -> Result<[f32; ACTION_DIM], EnvError> {
    let action: [f32; ACTION_DIM] = action.try_into().map_err(|_| EnvError::ActionDim {
        expected: ACTION_DIM,
        got: action.len(),
    })?;
    if let Some(index) = action.iter().position(|a| !a.is_finite()) {
        return Err(EnvError::NonFiniteAction {
            index,
            value: action[index],
        });
    }
    Ok(action.map(|a| a.clamp(-1.0, 1.0)))
}

impl Env for PointMaze {
    fn obs_dim(&self) -> usize {
        OBS_DIM
    }

    fn action_dim(&self) -> usize {
        ACTION_DIM
    }

    fn horizon(&self) -> usize {
        HORIZON
    }

    fn state_layout(&self) -> &StateLayout {
        &self.layout
    }

    fn reset_to_seed(
        &mut self,
        seed: Option<u64>,
        options: &serde_json::Value,
    ) -> Result<Vec<f32>, EnvError> {
        check_options(options)?;
        let cell = match seed {
            Some(seed) => {
                self.rng = ChaCha8Rng::seed_from_u64(seed);
                seed_cell(seed)
            }
            None => self.sample_cell(),
        };
        self.place(cell);
        Ok(self.obs())
    }

    fn reset_to_state(
        &mut self,
        seed: Option<u64>,
        options: &serde_json::Value,
        state: &[f32],
    ) -> Result<Vec<f32>, EnvError> {
        let (pos, vel, collided) = self.decode_state(state)?;
        self.reset_to_seed(seed, options)?;
        self.pos = pos;
        self.vel = vel;
        self.collided = collided;
        Ok(self.obs())
    }

    fn step(&mut self, action: &[f32]) -> Result<StepOutcome, EnvError> {
        let action = check_action(action)?;
        if self.trail.len() < TRAIL_MAX {
            self.trail.push(self.pos);
        }
        let mut vel = action.map(|a| a * MAX_SPEED);
        for _ in 0..SUBSTEPS {
            self.move_axis(0, &mut vel);
            self.move_axis(1, &mut vel);
            self.collided |= collides(self.pos);
        }
        self.vel = vel;
        Ok(StepOutcome {
            obs: self.obs(),
            success: self.is_success(),
        })
    }

    fn get_state(&self) -> Vec<f32> {
        let [x, y] = self.pos;
        let [vx, vy] = self.vel;
        vec![x, y, vx, vy, f32::from(u8::from(self.collided))]
    }

    fn render(&mut self) -> Result<Frame, EnvError> {
        Ok(draw::draw(&self.trail, self.pos, self.collided))
    }
}
