//! The PointMaze env (spec 7.5): resets, dynamics, success and collision rules, state round trips
//! and input errors.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rfcl_actor::pointmaze::{
    self, maze, PointMaze, COLLISION_MARGIN, GOAL_RADIUS, HORIZON, NEAR_GOAL_DISTANCE,
    POINT_RADIUS, START_JITTER,
};
use rfcl_actor::{Env, EnvError, StateKind};
use serde_json::{json, Value};

const NONE: &Value = &Value::Null;

/// A state at rest at `[x, y]` with the given collided flag.
fn state_at(x: f32, y: f32, collided: bool) -> Vec<f32> {
    vec![x, y, 0.0, 0.0, f32::from(u8::from(collided))]
}

/// An env restored to `state` (no seed).
fn env_at(state: &[f32]) -> PointMaze {
    let mut env = PointMaze::new(0);
    env.reset_to_state(None, NONE, state)
        .expect("a valid state");
    env
}

#[test]
fn dims_horizon_and_state_layout() {
    let env: Box<dyn Env> = Box::new(PointMaze::new(0));
    assert_eq!(
        (env.obs_dim(), env.action_dim(), env.horizon()),
        (7, 2, HORIZON)
    );
    assert_eq!(HORIZON, 300);
    let layout = env.state_layout();
    let entries: Vec<(&str, StateKind, usize, usize)> = layout
        .entries()
        .iter()
        .map(|e| (e.name.as_str(), e.kind, e.offset, e.len))
        .collect();
    let field = StateKind::Field;
    assert_eq!(
        entries,
        [
            ("qpos", field, 0, 2),
            ("qvel", field, 2, 2),
            ("collided", field, 4, 1)
        ]
    );
    assert_eq!(env.state_dim(), 5);
    assert_eq!(env.get_state().len(), 5);
    let state = [1.0, 2.0, 3.0, 4.0, 0.0];
    assert_eq!(layout.slice("qvel", &state), Some(&[3.0, 4.0][..]));
}

#[test]
fn seeded_reset_starts_at_rest_in_the_seed_cell_with_small_jitter() {
    let mut env = PointMaze::new(7);
    for seed in [0u64, 1, 5, 33, 34, 35, 1_000_003] {
        let obs = env.reset_to_seed(Some(seed), NONE).unwrap();
        let [cx, cy] = pointmaze::cell_centre(pointmaze::seed_cell(seed));
        assert!((obs[0] - cx).abs() <= START_JITTER && (obs[1] - cy).abs() <= START_JITTER);
        assert_eq!(
            &obs[2..],
            &[0.0, 0.0, 1.0, 1.0, 0.0],
            "at rest, goal (1, 1), no collision"
        );
        assert_eq!(env.cell(), pointmaze::seed_cell(seed));
        assert!(!env.is_success() && !pointmaze::collides(env.position()));
    }
}

#[test]
fn seeded_reset_is_deterministic_whatever_came_before() {
    let mut a = PointMaze::new(1);
    let mut b = PointMaze::new(2);
    b.reset_to_seed(None, NONE).unwrap();
    b.step(&[0.3, -0.2]).unwrap();
    for seed in [3u64, 3 + 34, 99] {
        assert_eq!(
            a.reset_to_seed(Some(seed), NONE),
            b.reset_to_seed(Some(seed), NONE)
        );
        // The env's RNG restarts from the seed, so the unseeded chain that follows matches too.
        for _ in 0..5 {
            assert_eq!(a.reset_to_seed(None, NONE), b.reset_to_seed(None, NONE));
        }
    }
    // Same cell, different seeds: different jitter.
    let first = a.reset_to_seed(Some(3), NONE).unwrap();
    let again = a.reset_to_seed(Some(3 + 34), NONE).unwrap();
    assert_ne!(first[..2], again[..2]);
    assert_eq!(a.cell(), pointmaze::seed_cell(3));
}

#[test]
fn unseeded_resets_follow_the_construction_seed_and_avoid_the_goal() {
    let mut a = PointMaze::new(11);
    let mut b = PointMaze::new(11);
    assert_eq!(a.get_state(), b.get_state(), "new() resets from its seed");
    let mut near = 0;
    let resets = 3000;
    for _ in 0..resets {
        let obs = a.reset_to_seed(None, &json!({})).unwrap();
        assert_eq!(Some(obs), b.reset_to_seed(None, NONE).ok());
        let cell = a.cell();
        assert!(pointmaze::start_cells().contains(&cell));
        near += usize::from(maze().distance_to_goal(cell).unwrap() <= NEAR_GOAL_DISTANCE);
    }
    // Uniform would put 5/34 ≈ 15% near the goal; redrawing with p = 0.95 leaves ≈ 0.9%.
    assert!(
        near < resets * 3 / 100,
        "{near} of {resets} unseeded resets near the goal"
    );
    assert!(near > 0, "near cells are rare, not impossible");
    assert_ne!(
        PointMaze::new(12).get_state(),
        PointMaze::new(11).get_state()
    );
}

#[test]
fn actions_set_velocity_for_ten_substeps_then_no_momentum() {
    // Row 4 is a horizontal corridor: (4, 4) has walls above and below.
    let mut env = env_at(&state_at(4.0, 4.0, false));
    let out = env.step(&[1.0, 0.0]).unwrap();
    assert!(
        (out.obs[0] - 4.2).abs() < 1e-5,
        "x moves 0.2 per full step, got {}",
        out.obs[0]
    );
    assert_eq!((out.obs[1], out.obs[2], out.obs[3]), (4.0, 2.0, 0.0));
    let out = env.step(&[0.0, 0.0]).unwrap();
    assert!((out.obs[0] - 4.2).abs() < 1e-5, "a zero action stays put");
    assert_eq!(&out.obs[2..4], &[0.0, 0.0]);
    // Out-of-range actions are clipped to [-1, 1].
    let mut clipped = env.clone();
    let a = env.step(&[-7.0, 0.0]).unwrap();
    let b = clipped.step(&[-1.0, 0.0]).unwrap();
    assert_eq!(a, b);
}

#[test]
fn success_is_distance_at_most_045_without_collision() {
    // East of the goal lies the open cell (1, 2), so no wall is within the margin there.
    let inside = GOAL_RADIUS - 0.01;
    let mut env = env_at(&state_at(1.0 + inside, 1.0, false));
    assert!(env.is_success());
    assert!(
        env.step(&[0.0, 0.0]).unwrap().success,
        "success is judged after the step"
    );
    let mut env = env_at(&state_at(1.0 + GOAL_RADIUS + 0.01, 1.0, false));
    assert!(!env.step(&[0.0, 0.0]).unwrap().success);
    // At the goal but collided earlier: never a success.
    let mut env = env_at(&state_at(1.0, 1.0, true));
    let out = env.step(&[0.0, 0.0]).unwrap();
    assert!(!out.success);
    assert_eq!(out.obs[6], 1.0);
    // Walking into the goal from a clean state succeeds.
    let mut env = env_at(&state_at(2.0, 1.0, false));
    let steps: Vec<bool> = (0..4)
        .map(|_| env.step(&[-1.0, 0.0]).unwrap().success)
        .collect();
    assert_eq!(steps, [false, false, true, true], "x: 1.8, 1.6, 1.4, 1.2");
}

#[test]
fn collision_is_within_065_of_a_hazard_centre_on_both_axes_and_sticks() {
    // Cell (3, 10): the hazard (2, 10) is centred at y = 2 above it.
    assert!(!pointmaze::collides([10.0, 2.0 + COLLISION_MARGIN + 0.01]));
    assert!(pointmaze::collides([10.0, 2.0 + COLLISION_MARGIN - 0.01]));
    // The goal cell (1, 1): the hazard (1, 0) is centred at x = 0.
    assert!(!pointmaze::collides([COLLISION_MARGIN + 0.01, 1.0]));
    assert!(pointmaze::collides([COLLISION_MARGIN - 0.01, 1.0]));
    // Cell (10, 6): the hazard (10, 5) is centred at x = 5; within the margin in x alone (the point
    // further up, in the wall (9, 6)'s rows) is no collision.
    assert!(!pointmaze::collides([5.0 + COLLISION_MARGIN + 0.05, 10.0]));
    assert!(pointmaze::collides([5.0 + COLLISION_MARGIN - 0.01, 10.0]));
    assert!(pointmaze::collides([-3.0, 1.0]), "outside the grid");
    // Plain walls block but do not count: cell (1, 2) lies between the walls (0, 2) and (2, 2).
    assert!(!pointmaze::collides([2.0, 2.0 - COLLISION_MARGIN + 0.01]));
    assert!(!pointmaze::collides([2.0, COLLISION_MARGIN - 0.01]));
    assert!(!pointmaze::collides([8.0 - COLLISION_MARGIN + 0.01, 3.3]));

    let mut env = env_at(&state_at(0.8, 1.0, false));
    let out = env.step(&[-0.5, 0.0]).unwrap();
    assert!((out.obs[0] - 0.7).abs() < 1e-5);
    assert_eq!(
        out.obs[6], 0.0,
        "x = 0.7 is 0.7 from the hazard centre at x = 0"
    );
    let out = env.step(&[-0.5, 0.0]).unwrap();
    assert!((out.obs[0] - 0.6).abs() < 1e-5);
    assert_eq!(
        out.obs[6], 1.0,
        "x = 0.6 is 0.6 from the hazard centre at x = 0"
    );
    // Back to the goal: the flag stays and there is no success.
    for _ in 0..10 {
        let dir = [1.0 - env.position()[0], 1.0 - env.position()[1]];
        let out = env.step(&dir.map(|d| (d / 0.2).clamp(-1.0, 1.0))).unwrap();
        assert!(!out.success && out.obs[6] == 1.0);
    }
    assert!(pointmaze::at_goal(env.position()));
}

#[test]
fn walls_block_the_point_at_its_radius() {
    let mut env = env_at(&state_at(2.0, 1.3, false));
    for _ in 0..5 {
        env.step(&[0.0, 1.0]).unwrap();
    }
    let face = 2.0 - 0.5 - POINT_RADIUS;
    assert_eq!(
        env.position(),
        [2.0, face],
        "stopped at the face of wall (2, 2)"
    );
    assert_eq!(
        &env.obs()[2..4],
        &[0.0, 0.0],
        "the blocked axis lost its velocity"
    );
    // Sliding along the wall: the free axis still moves.
    let out = env.step(&[1.0, 1.0]).unwrap();
    assert!((out.obs[0] - 2.2).abs() < 1e-5 && out.obs[1] == face);
    assert_eq!((out.obs[2], out.obs[3]), (2.0, 0.0));
    // A point never leaves the maze, whatever it is told.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut env = PointMaze::new(5);
    for _ in 0..2000 {
        let action = [rng.random_range(-1.0..=1.0), rng.random_range(-1.0..=1.0)];
        env.step(&action).unwrap();
        let cell = pointmaze::cell_at(env.position()).expect("inside the grid");
        assert!(!maze().is_wall(cell), "the point entered wall {cell:?}");
    }
}

#[test]
fn reset_to_state_round_trips_and_steps_like_the_original() {
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let mut original = PointMaze::new(3);
    original.reset_to_seed(Some(29), NONE).unwrap();
    let actions: Vec<[f32; 2]> = (0..60)
        .map(|_| [rng.random_range(-1.0..=1.0), rng.random_range(-1.0..=1.0)])
        .collect();
    let mut checked_collided = false;
    for (t, action) in actions.iter().enumerate().step_by(7) {
        let mut probe = original.clone();
        for a in &actions[..t] {
            probe.step(a).unwrap();
        }
        let state = probe.get_state();
        let mut restored = PointMaze::new(1000 + t as u64);
        let obs = restored.reset_to_state(Some(29), NONE, &state).unwrap();
        assert_eq!(restored.get_state(), state, "exact round trip at t = {t}");
        assert_eq!(obs, probe.obs());
        for a in std::iter::once(action).chain(&actions[t + 1..]) {
            assert_eq!(restored.step(a).unwrap(), probe.step(a).unwrap());
        }
        assert_eq!(restored.get_state(), probe.get_state());
        checked_collided |= state[4] == 1.0;
    }
    assert!(
        checked_collided,
        "random actions collide, so a collided state was restored"
    );
}

#[test]
fn reset_to_state_resets_with_the_seed_first() {
    let state = state_at(4.0, 4.0, false);
    let mut a = PointMaze::new(1);
    let mut b = PointMaze::new(2);
    a.reset_to_state(Some(8), NONE, &state).unwrap();
    b.reset_to_seed(Some(8), NONE).unwrap();
    assert_eq!(a.get_state(), state);
    assert_eq!(
        a.reset_to_seed(None, NONE),
        b.reset_to_seed(None, NONE),
        "same RNG afterwards"
    );
}

#[test]
fn bad_actions_are_named() {
    let mut env = PointMaze::new(0);
    let before = env.get_state();
    let err = env.step(&[0.1, 0.2, 0.3]).unwrap_err();
    assert!(
        matches!(
            err,
            EnvError::ActionDim {
                expected: 2,
                got: 3
            }
        ),
        "{err}"
    );
    assert!(matches!(
        env.step(&[]),
        Err(EnvError::ActionDim {
            expected: 2,
            got: 0
        })
    ));
    let err = env.step(&[0.0, f32::NAN]).unwrap_err();
    assert!(
        matches!(err, EnvError::NonFiniteAction { index: 1, .. }),
        "{err}"
    );
    assert!(matches!(
        env.step(&[f32::INFINITY, 0.0]),
        Err(EnvError::NonFiniteAction { index: 0, .. })
    ));
    assert_eq!(env.get_state(), before, "a refused action changes nothing");
    assert_eq!(
        err.to_string(),
        "action component 1 is NaN, not a finite number"
    );
}

#[test]
fn bad_states_and_options_are_named() {
    let mut env = PointMaze::new(0);
    let before = env.get_state();
    let mut reject = |state: &[f32]| env.reset_to_state(Some(1), NONE, state).unwrap_err();
    let invalid_field = |err: &EnvError| match err {
        EnvError::InvalidState { field, .. } => field.clone(),
        other => panic!("expected InvalidState, got {other}"),
    };

    let err = reject(&[4.0, 4.0, 0.0, 0.0]);
    assert!(
        matches!(
            err,
            EnvError::StateLen {
                expected: 5,
                got: 4
            }
        ),
        "{err}"
    );
    assert_eq!(
        invalid_field(&reject(&[4.0, f32::NAN, 0.0, 0.0, 0.0])),
        "qpos"
    );
    assert_eq!(
        invalid_field(&reject(&[4.0, 4.0, f32::INFINITY, 0.0, 0.0])),
        "qvel"
    );
    assert_eq!(
        invalid_field(&reject(&[4.0, 4.0, 0.0, 0.0, 0.5])),
        "collided"
    );
    assert_eq!(
        invalid_field(&reject(&state_at(3.0, 3.0, true))),
        "qpos",
        "inside a wall"
    );
    assert_eq!(
        invalid_field(&reject(&state_at(20.0, 3.0, true))),
        "qpos",
        "outside"
    );
    let err = reject(&state_at(0.6, 1.0, false));
    assert_eq!(
        invalid_field(&err),
        "collided",
        "within the margin but not collided: {err}"
    );
    assert!(err.to_string().contains("hazard wall cell (1, 0)"), "{err}");
    assert_eq!(env.get_state(), before, "a refused state changes nothing");
    assert!(env
        .reset_to_state(Some(1), NONE, &state_at(0.6, 1.0, true))
        .is_ok());

    let err = env
        .reset_to_seed(Some(1), &json!({"goal": [1, 2]}))
        .unwrap_err();
    assert!(matches!(err, EnvError::InvalidOptions { .. }), "{err}");
    assert!(env.reset_to_seed(Some(1), &json!({})).is_ok());
}

#[test]
fn random_actions_rarely_reach_the_goal_from_far_cells() {
    // The reverse curriculum matters: exploration from the far half of the maze is hopeless.
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut env = PointMaze::new(9);
    let far_seeds: Vec<u64> = (0..34u64)
        .filter(|&s| maze().distance_to_goal(pointmaze::seed_cell(s)).unwrap() >= 10)
        .collect();
    for &seed in &far_seeds {
        env.reset_to_seed(Some(seed), NONE).unwrap();
        for _ in 0..HORIZON {
            let action = [rng.random_range(-1.0..=1.0), rng.random_range(-1.0..=1.0)];
            assert!(
                !env.step(&action).unwrap().success,
                "seed {seed} succeeded at random"
            );
        }
    }
}
