//! The env trait: what an actor needs from a simulator.
//!
//! An [`Env`] is one simulator instance stepped by one actor. It knows nothing about rewards,
//! time limits or curricula:
//!
//! * **Reward** is computed by the actor as `+1` on every step whose resulting state is a success
//!   state, from [`StepOutcome::success`] (spec 5.6). The env's own reward, if it has one, is unused.
//! * **Episodes never end on success** (spec 5.6). Truncation at [`Env::horizon`] or at the dynamic
//!   time limit of stage 1 (spec 2.5) is the actor's job; an env keeps stepping as long as it is asked.
//! * **Resets** come in two kinds: to a seed (a level of the forward curriculum or an initial state of
//!   the task distribution, spec 2.4 step 3 and 3.1) and to a demo state (spec 2.4 steps 3-6).
//!
//! The env state is an opaque `f32` vector whose flattening each env documents in its
//! [`StateLayout`]: the same type that describes the
//! `env_states` of a demo file, so that an env and a demo set can be checked against each other.
//! Geometry and goals may live outside that vector, which is why restoring a state always starts
//! with a reset to the demo's seed and options (spec 2.4, 12.13).
//!
//! The native PointMaze ([`crate::pointmaze::PointMaze`]) implements the trait in Rust; the
//! ManiSkill, MetaWorld and Adroit adapters implement it through Python workers.

pub use rfcl_core::demo::{StateEntry, StateKind, StateLayout};

pub use crate::video::Frame;

/// Why an env refused a call. Each variant names what was wrong with the input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EnvError {
    /// The action does not have [`Env::action_dim`] components.
    #[error("action has {got} components, the env takes {expected}")]
    ActionDim { expected: usize, got: usize },
    /// An action component is NaN or infinite.
    #[error("action component {index} is {value}, not a finite number")]
    NonFiniteAction { index: usize, value: f32 },
    /// The state does not have as many values as the env's [`StateLayout`].
    #[error("state has {got} values, the env's state layout has {expected}")]
    StateLen { expected: usize, got: usize },
    /// A state value is out of its domain, or the state is not physically consistent.
    #[error("state field `{field}` is invalid: {reason}")]
    InvalidState { field: String, reason: String },
    /// The reset options are not ones this env understands.
    #[error("reset options are invalid: {reason}")]
    InvalidOptions { reason: String },
    /// The env was made without a renderer ([`Env::render`]).
    #[error("this env has no renderer{hint}")]
    NoRenderer { hint: String },
    /// The simulator behind the env failed: a Python exception (the message carries its
    /// traceback), or a worker process that crashed or hung twice in a row (crate::python).
    #[error("the simulator failed: {message}")]
    Simulator { message: String },
}

/// The result of one [`Env::step`].
#[derive(Debug, Clone, PartialEq)]
pub struct StepOutcome {
    /// Observation of the state after the action, [`Env::obs_dim`] values.
    pub obs: Vec<f32>,
    /// Whether the state after the action is a success state. The actor's sparse reward is
    /// `success as u8` on every step (spec 5.6, 12.6).
    pub success: bool,
}

/// A simulator instance stepped by an actor. Object safe: actors hold `Box<dyn Env>`.
pub trait Env: Send {
    /// Length of every observation.
    fn obs_dim(&self) -> usize;

    /// Length of every action. Actions are in `[-1, 1]` per component (the agent's units).
    fn action_dim(&self) -> usize;

    /// The task's horizon H: the actor truncates episodes after H steps (spec 5.6, 8.3).
    fn horizon(&self) -> usize;

    /// How [`Env::get_state`] flattens the state.
    fn state_layout(&self) -> &StateLayout;

    /// Length of the state vector.
    fn state_dim(&self) -> usize {
        self.state_layout().dim()
    }

    /// Resets to an initial state and returns its observation (spec 2.4 step 3, 3.1).
    ///
    /// With `Some(seed)` the initial state is a deterministic function of `seed` and `options`, and
    /// the env's RNG restarts from `seed`. With `None` the env draws from its own RNG, continuing
    /// its chain.
    fn reset_to_seed(
        &mut self,
        seed: Option<u64>,
        options: &serde_json::Value,
    ) -> Result<Vec<f32>, EnvError>;

    /// Resets to a stored state (a demo state, spec 2.4 steps 3-6) and returns its observation.
    ///
    /// Implementations first reset exactly as [`Env::reset_to_seed`] with the demo's `seed` and
    /// `options` (which restores randomisation the state vector does not carry), **then** set the
    /// state (spec 12.13). Afterwards [`Env::get_state`] returns `state` unchanged.
    fn reset_to_state(
        &mut self,
        seed: Option<u64>,
        options: &serde_json::Value,
        state: &[f32],
    ) -> Result<Vec<f32>, EnvError>;

    /// Applies one action and reports the new observation and whether it is a success state.
    /// Never terminates the episode (spec 5.6).
    fn step(&mut self, action: &[f32]) -> Result<StepOutcome, EnvError>;

    /// The current state, laid out as [`Env::state_layout`] says.
    fn get_state(&self) -> Vec<f32>;

    /// The current state as an image, from the simulator's own renderer (PointMaze: drawn by
    /// rfcl), for eval videos. Python envs render only when made with a frame size
    /// ([`crate::suite::make_env`]); envs without a renderer say so.
    fn render(&mut self) -> Result<Frame, EnvError> {
        Err(EnvError::NoRenderer {
            hint: String::new(),
        })
    }

    /// Simulator worker restarts so far: a Python env restarts a crashed or hung worker and
    /// replays the episode in flight (crate::python), which the actor reports so that the run
    /// sees it. Native envs never restart.
    fn restarts(&self) -> u64 {
        0
    }
}
