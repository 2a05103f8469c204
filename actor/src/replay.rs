//! A demo's quality check with no run (`rfcl demos inspect --replay`), judging what a reverse
//! curriculum needs of it (docs/SUITES.md "Checking demos"):
//!
//! 1. **every state restores exactly**: the env accepts it as a reset state, and reading the state
//!    back gives it unchanged (within [`RESTORE_TOLERANCE`]);
//! 2. **every step replays**: from each restored state t, the demo's action t leads to its state
//!    t+1, with positions within [`POSITION_TOLERANCE`] and orientations within
//!    [`ORIENTATION_TOLERANCE`], and to its success flag t;
//! 3. **it ends in a success**: the env's own check after the last step.
//!
//! Velocities are measured and reported but not judged. In contact-rich simulations (ManiSkill3's
//! PhysX) the solver keeps state that no state vector carries (contact caches, warm starts), so two
//! replays of the same actions from the same restored state already differ in a grasped object's
//! angular velocity by several rad/s, while positions agree to a few millimetres; a velocity that
//! is really wrong shows in the next state's positions. For the same reason the open-loop replay of
//! all actions from the first state is reported (its success at the end and its largest position
//! drift), not judged: ManiSkill's own `replay_trajectory` is this replay.
use rfcl_core::demo::{Demo, Quantity, StatePart};

use crate::env::{Env, EnvError};

/// Largest difference between a state and the state read back after restoring it.
pub const RESTORE_TOLERANCE: f32 = 1e-5;
/// Largest one-step error of a position (metres), joint position (radians or metres) or other
/// configuration value. ManiSkill3's motion-planned demos of StackCube, PegInsertionSide and
/// PlugCharger stay within 3.3e-3 (joints in contact) and 2.1e-3 m (objects).
pub const POSITION_TOLERANCE: f32 = 0.01;
/// Largest one-step error of an orientation: the angle between the two rotations, in radians
/// (measured on the same demos: up to about 0.02).
pub const ORIENTATION_TOLERANCE: f32 = 0.05;
/// Largest one-step error of an entry of an opaque flat (MS2) state, whose kinds are unknown.
pub const VALUE_TOLERANCE: f32 = 1e-3;

/// The tolerance a quantity is judged with; `None` for velocities, which are only reported.
pub fn tolerance(quantity: Quantity) -> Option<f32> {
    match quantity {
        Quantity::Position => Some(POSITION_TOLERANCE),
        Quantity::Orientation => Some(ORIENTATION_TOLERANCE),
        Quantity::Velocity => None,
        Quantity::Value => Some(VALUE_TOLERANCE),
    }
}

/// The largest error of one quantity over a demo, and where it was.
#[derive(Debug, Clone, PartialEq)]
pub struct Worst {
    pub error: f32,
    /// The part, e.g. `actors/cubeA position`.
    pub part: String,
    /// The demo state that was reached with this error.
    pub state: usize,
}

/// What checking one demo found.
#[derive(Debug, Clone, PartialEq)]
pub struct ReplayCheck {
    /// The first state the env refuses as a reset state: (index, why).
    pub invalid_state: Option<(usize, String)>,
    /// The largest difference between a state and the state read back after restoring it.
    pub restore_error: f32,
    /// The first state that does not read back within [`RESTORE_TOLERANCE`].
    pub unrestored_state: Option<usize>,
    /// Per quantity, the largest one-step error (from restored state t to state t+1).
    pub one_step: Vec<(Quantity, Worst)>,
    /// The first one-step error beyond its quantity's tolerance.
    pub first_violation: Option<(Quantity, Worst)>,
    /// Steps whose replayed success flag differs from the demo's.
    pub success_mismatches: usize,
    /// The env's own success check after the last step, from the last state but one.
    pub final_success: bool,
    /// The open-loop replay of every action from the first state (reported, not judged).
    pub open_loop: OpenLoop,
}

/// The open-loop replay of a demo's actions from its first state.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct OpenLoop {
    /// Whether it ends in a success.
    pub success_at_end: bool,
    /// Its largest position error against the demo's states.
    pub max_position_error: f32,
}

impl ReplayCheck {
    /// Whether the demo passes every judged check.
    pub fn passed(&self) -> bool {
        self.invalid_state.is_none()
            && self.unrestored_state.is_none()
            && self.first_violation.is_none()
            && self.success_mismatches == 0
            && self.final_success
    }

    /// The largest one-step error of `quantity`, if the layout has it.
    pub fn worst(&self, quantity: Quantity) -> Option<&Worst> {
        self.one_step
            .iter()
            .find(|(q, _)| *q == quantity)
            .map(|(_, w)| w)
    }
}

/// Checks `demo` on `env` (spec 2.4: each reset first resets with the demo's seed and options).
/// Fails only when the simulator itself fails; a refused state is a finding, not an error.
pub fn check_demo(env: &mut dyn Env, demo: &Demo) -> Result<ReplayCheck, EnvError> {
    let parts = env.state_layout().parts();
    let states: Vec<&[f32]> = demo.env_states.chunks_exact(demo.state_dim).collect();
    let actions: Vec<&[f32]> = demo.actions.chunks_exact(demo.action_dim).collect();
    let mut check = ReplayCheck {
        invalid_state: None,
        restore_error: 0.0,
        unrestored_state: None,
        one_step: Vec::new(),
        first_violation: None,
        success_mismatches: 0,
        final_success: false,
        open_loop: OpenLoop::default(),
    };
    for (t, state) in states.iter().enumerate() {
        if let Some(why) = refused_as_reset_state(env, demo, state)? {
            check.invalid_state = Some((t, why));
            return Ok(check);
        }
        let restored = max_abs_difference(&env.get_state(), state);
        check.restore_error = check.restore_error.max(restored);
        if restored > RESTORE_TOLERANCE && check.unrestored_state.is_none() {
            check.unrestored_state = Some(t);
        }
        let Some(action) = actions.get(t) else { break };
        let outcome = env.step(action)?;
        let reached = env.get_state();
        for (part, error) in part_errors(&parts, &reached, states[t + 1]) {
            check.record(part, error, t + 1);
        }
        check.success_mismatches += usize::from(outcome.success != demo.success[t]);
        check.final_success = outcome.success;
    }
    check.open_loop = open_loop(env, demo, &parts, &states, &actions)?;
    Ok(check)
}

/// Why `env` refuses `state` of `demo` as a reset state (after the demo's seed and options), or
/// `None` when it takes it. Fails only when the simulator itself fails.
pub fn refused_as_reset_state(
    env: &mut dyn Env,
    demo: &Demo,
    state: &[f32],
) -> Result<Option<String>, EnvError> {
    match env.reset_to_state(demo.reset.seed, &demo.reset.options, state) {
        Ok(_) => Ok(None),
        Err(EnvError::Simulator { message }) => Err(EnvError::Simulator { message }),
        Err(e) => Ok(Some(e.to_string())),
    }
}

/// The first state of any demo of `demos` that `env` refuses as a reset state: (demo index, its
/// episode id, state index, why). Every state is tried, in order; one on which the simulator
/// fails (a Python exception, a worker that dies) is refused with the simulator's error.
pub fn first_refused_state(
    env: &mut dyn Env,
    demos: &[Demo],
) -> Option<(usize, u64, usize, String)> {
    for (i, demo) in demos.iter().enumerate() {
        for (t, state) in demo.env_states.chunks_exact(demo.state_dim).enumerate() {
            if let Err(e) = env.reset_to_state(demo.reset.seed, &demo.reset.options, state) {
                return Some((i, demo.episode_id, t, e.to_string()));
            }
        }
    }
    None
}

impl ReplayCheck {
    fn record(&mut self, part: &StatePart, error: f32, state: usize) {
        let worst = Worst {
            error,
            part: part.name.clone(),
            state,
        };
        if self.first_violation.is_none() && tolerance(part.quantity).is_some_and(|t| error > t) {
            self.first_violation = Some((part.quantity, worst.clone()));
        }
        match self.one_step.iter_mut().find(|(q, _)| *q == part.quantity) {
            Some((_, w)) if w.error >= error => {}
            Some((_, w)) => *w = worst,
            None => self.one_step.push((part.quantity, worst)),
        }
    }
}

fn open_loop(
    env: &mut dyn Env,
    demo: &Demo,
    parts: &[StatePart],
    states: &[&[f32]],
    actions: &[&[f32]],
) -> Result<OpenLoop, EnvError> {
    env.reset_to_state(demo.reset.seed, &demo.reset.options, states[0])?;
    let mut replay = OpenLoop::default();
    for (t, action) in actions.iter().enumerate() {
        replay.success_at_end = env.step(action)?.success;
        let reached = env.get_state();
        for (part, error) in part_errors(parts, &reached, states[t + 1]) {
            if part.quantity == Quantity::Position {
                replay.max_position_error = replay.max_position_error.max(error);
            }
        }
    }
    Ok(replay)
}

/// Each part's error between two states: the angle between rotations for orientations, the
/// largest absolute difference otherwise (infinite when the states' lengths differ).
fn part_errors<'a>(
    parts: &'a [StatePart],
    a: &'a [f32],
    b: &'a [f32],
) -> impl Iterator<Item = (&'a StatePart, f32)> + 'a {
    parts.iter().map(move |part| {
        let (Some(x), Some(y)) = (a.get(part.range.clone()), b.get(part.range.clone())) else {
            return (part, f32::INFINITY);
        };
        let error = match part.quantity {
            Quantity::Orientation => rotation_angle(x, y),
            _ => max_abs_difference(x, y),
        };
        (part, error)
    })
}

/// The angle in radians of the rotation between two quaternions (either sign of each).
pub fn rotation_angle(a: &[f32], b: &[f32]) -> f32 {
    let norm = |q: &[f32]| q.iter().map(|v| f64::from(*v).powi(2)).sum::<f64>().sqrt();
    let dot: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| f64::from(*x) * f64::from(*y))
        .sum();
    let cos_half = (dot.abs() / (norm(a) * norm(b))).min(1.0);
    if !cos_half.is_finite() {
        return f32::INFINITY;
    }
    (2.0 * cos_half.acos()) as f32
}

/// The largest absolute difference between two vectors (infinite when their lengths differ).
fn max_abs_difference(a: &[f32], b: &[f32]) -> f32 {
    if a.len() != b.len() {
        return f32::INFINITY;
    }
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// The one-line verdict on a demo for `rfcl demos inspect --replay`: `Ok` with the errors
/// measured, or `Err` with every problem found.
pub fn verdict(check: &ReplayCheck, states: usize) -> Result<String, String> {
    let mut problems = Vec::new();
    if let Some((index, why)) = &check.invalid_state {
        problems.push(format!("state {index} is not a valid reset state: {why}"));
    }
    if let Some(t) = check.unrestored_state {
        problems.push(format!(
            "state {t} does not restore exactly (it reads back {:.1e} off, more than {RESTORE_TOLERANCE:e})",
            check.restore_error
        ));
    }
    if let Some((quantity, w)) = &check.first_violation {
        let tol = tolerance(*quantity).unwrap_or(0.0);
        problems.push(format!(
            "one step from state {} misses state {} ({} off by {:.2e}, tolerance {tol})",
            w.state - 1,
            w.state,
            w.part,
            w.error
        ));
    }
    if check.success_mismatches > 0 {
        problems.push(format!(
            "{} success flags differ from the replay's",
            check.success_mismatches
        ));
    }
    if check.invalid_state.is_none() && !check.final_success {
        problems.push("its final state is not a success".into());
    }
    if !problems.is_empty() {
        return Err(problems.join("; "));
    }
    let mut measured: Vec<String> = check
        .one_step
        .iter()
        .map(|(q, w)| format!("{} {:.1e}", quantity_name(*q), w.error))
        .collect();
    measured.sort();
    let open = if check.open_loop.success_at_end {
        "succeeds"
    } else {
        "does not succeed"
    };
    Ok(format!(
        "{states} states restore exactly, one-step errors: {}; open loop from state 0 {open} \
         (positions within {:.1e})",
        measured.join(", "),
        check.open_loop.max_position_error
    ))
}

fn quantity_name(q: Quantity) -> &'static str {
    match q {
        Quantity::Position => "position",
        Quantity::Orientation => "orientation",
        Quantity::Velocity => "velocity (not judged)",
        Quantity::Value => "value",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pointmaze::demos::{demo_set, generate_demos};
    use crate::PointMaze;

    #[test]
    fn generated_pointmaze_demos_pass_and_a_moved_state_or_a_cut_demo_is_caught() {
        let set = demo_set(generate_demos(2, 0), "unused.h5");
        let mut env = PointMaze::new(0);
        for demo in &set.demos {
            let check = check_demo(&mut env, demo).unwrap();
            assert!(check.passed(), "{check:?}");
            assert!(check.restore_error <= RESTORE_TOLERANCE);
            assert!(check.worst(Quantity::Position).unwrap().error <= 1e-5);
            assert!(check.open_loop.success_at_end);
            assert!(verdict(&check, demo.len() + 1).is_ok());
        }
        // A state moved one cell along its corridor: the step into it misses it.
        let mut moved = set.demos[0].clone();
        let t = moved.len() / 2;
        moved.env_states[t * moved.state_dim] += 1.0;
        let check = check_demo(&mut env, &moved).unwrap();
        assert!(!check.passed());
        let (quantity, worst) = check.first_violation.clone().unwrap();
        assert_eq!((quantity, worst.state), (Quantity::Position, t));
        assert_eq!(worst.part, "qpos");
        let why = verdict(&check, moved.len() + 1).unwrap_err();
        assert!(
            why.contains(&format!(
                "one step from state {} misses state {t} (qpos off by",
                t - 1
            )),
            "{why}"
        );
        // A state inside a wall is refused as a reset state, with the field named.
        let mut walled = set.demos[0].clone();
        walled.env_states[..2].copy_from_slice(&[0.0, 0.0]);
        let check = check_demo(&mut env, &walled).unwrap();
        let (index, why) = check.invalid_state.clone().unwrap();
        assert_eq!(index, 0);
        assert!(why.contains("qpos"), "{why}");
        // Cut half-way: every step replays, but its final state is no success.
        let mut cut = set.demos[0].clone();
        let keep = cut.len() / 2;
        cut.actions.truncate(keep * cut.action_dim);
        cut.success.truncate(keep);
        cut.env_states.truncate((keep + 1) * cut.state_dim);
        let check = check_demo(&mut env, &cut).unwrap();
        assert!(check.first_violation.is_none() && check.success_mismatches == 0);
        assert!(!check.final_success && !check.passed(), "{check:?}");
        // A flipped success flag is counted.
        let mut flipped = set.demos[0].clone();
        flipped.success[0] = !flipped.success[0];
        let check = check_demo(&mut env, &flipped).unwrap();
        assert_eq!(check.success_mismatches, 1);
        assert!(!check.passed());
    }

    #[test]
    fn velocities_are_reported_but_not_judged() {
        let set = demo_set(generate_demos(1, 0), "unused.h5");
        let mut env = PointMaze::new(0);
        // PointMaze's qvel is a velocity: changing a recorded velocity alone changes no position
        // the next step reaches from the restored state before it, so only its error grows.
        let mut fast = set.demos[0].clone();
        let t = fast.len() - 1;
        fast.env_states[t * fast.state_dim + 2] += 5.0;
        let check = check_demo(&mut env, &fast).unwrap();
        let worst = check.worst(Quantity::Velocity).unwrap();
        assert_eq!((worst.part.as_str(), worst.state), ("qvel", t));
        assert!(worst.error >= 4.9, "{worst:?}");
        assert!(check.first_violation.is_none(), "{check:?}");
    }

    #[test]
    fn rotation_angle_by_hand() {
        // Identity against a 90° turn about z: (cos 45°, 0, 0, sin 45°).
        let h = std::f32::consts::FRAC_1_SQRT_2;
        let angle = rotation_angle(&[1.0, 0.0, 0.0, 0.0], &[h, 0.0, 0.0, h]);
        assert!(
            (angle - std::f32::consts::FRAC_PI_2).abs() < 1e-6,
            "{angle}"
        );
        // q and −q are the same rotation.
        assert!(rotation_angle(&[h, 0.0, 0.0, h], &[-h, 0.0, 0.0, -h]) < 1e-3);
        assert_eq!(
            rotation_angle(&[1.0, 0.0, 0.0, 0.0], &[1.0, 0.0, 0.0, 0.0]),
            0.0
        );
    }
}
