//! The Python bridge with the real simulator: ManiSkill3 through `rfcl-sim-worker` processes.
//!
//! * a state round trip (set, then get) for each of the four ManiSkill3 tasks (spec 7.1, 12.13);
//! * a killed worker is detected, restarted, and the episode in flight goes on where it was; a hung
//!   one is killed at the call deadline and replaced the same way;
//! * Python exceptions reach Rust with their traceback, at start-up and during a reset;
//! * a worker made with a frame size renders the simulator's frames (eval videos); one without
//!   says how to get one.
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rfcl_actor::env::{Env, EnvError};
use rfcl_actor::python::{PythonEnv, PythonEnvError, WorkerSpec};
use rfcl_testkit::child::{signal, Signal};
use serde_json::json;

fn spec(env_id: &str, options: serde_json::Value) -> WorkerSpec {
    WorkerSpec {
        suite: "maniskill3".into(),
        env_id: env_id.into(),
        options,
        program: env!("CARGO_BIN_EXE_rfcl-sim-worker").into(),
    }
}

fn actions(n: usize, dim: usize, seed: u64) -> Vec<Vec<f32>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| (0..dim).map(|_| rng.random_range(-1.0..1.0)).collect())
        .collect()
}

fn max_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn states_round_trip_through_the_bridge_for_each_task() {
    // (task, obs dim, horizon): dims from the adapter, horizons ManiSkill registers.
    for (env_id, obs_dim, horizon) in [
        ("PickCube-v1", 42, 50),
        ("StackCube-v1", 48, 50),
        ("PegInsertionSide-v1", 43, 100),
        ("PlugCharger-v1", 46, 200),
    ] {
        let mut env = PythonEnv::start(spec(env_id, json!({})), 11).unwrap();
        assert_eq!(
            (env.obs_dim(), env.action_dim(), env.horizon()),
            (obs_dim, 8, horizon),
            "{env_id}"
        );
        let layout = env.state_layout().clone();
        assert!(
            layout.entries()[0].name.starts_with("actors/"),
            "{env_id}: {layout:?}"
        );
        assert_eq!(
            layout.entries().last().unwrap().dof(),
            Some(9),
            "{env_id}: the panda's 7 joints and 2 fingers last"
        );
        env.reset_to_seed(Some(4), &json!({})).unwrap();
        for a in actions(4, 8, 1) {
            let out = env.step(&a).unwrap();
            assert_eq!(out.obs.len(), obs_dim);
        }
        let state = env.get_state();
        assert_eq!(state.len(), layout.dim());
        // Elsewhere first, then back to the state (after a reset to the same seed, spec 12.13).
        env.reset_to_seed(Some(9), &json!({})).unwrap();
        assert!(
            max_diff(&env.get_state(), &state) > 1e-3,
            "{env_id}: a different state"
        );
        let obs = env.reset_to_state(Some(4), &json!({}), &state).unwrap();
        assert_eq!(obs.len(), obs_dim);
        let back = env.get_state();
        assert!(
            max_diff(&back, &state) <= 1e-6,
            "{env_id}: {back:?} vs {state:?}"
        );
        assert_eq!(env.restarts(), 0);
    }
}

#[test]
fn a_killed_worker_is_restarted_and_the_episode_goes_on() {
    let acts = actions(12, 8, 2);
    // The reference: one worker, never interrupted.
    let mut reference = PythonEnv::start(spec("PickCube-v1", json!({})), 5).unwrap();
    reference.reset_to_seed(Some(3), &json!({})).unwrap();
    let expected: Vec<_> = acts.iter().map(|a| reference.step(a).unwrap()).collect();

    let mut env = PythonEnv::start(spec("PickCube-v1", json!({})), 5).unwrap();
    env.reset_to_seed(Some(3), &json!({})).unwrap();
    for a in &acts[..6] {
        env.step(a).unwrap();
    }
    let pid = env.worker_pid().unwrap();
    signal(pid, Signal::KILL);
    // The next step finds the worker dead, restarts it, replays reset + 6 steps, and steps.
    for (i, a) in acts.iter().enumerate().skip(6) {
        let out = env.step(a).unwrap();
        assert!(
            max_diff(&out.obs, &expected[i].obs) < 1e-4,
            "step {i} after the restart"
        );
        assert_eq!(out.success, expected[i].success);
    }
    assert_eq!(env.restarts(), 1);
    assert_ne!(env.worker_pid(), Some(pid));
    // The dead worker was reaped (a zombie would still have a /proc entry).
    assert!(!std::path::Path::new(&format!("/proc/{pid}")).exists());
}

#[test]
fn a_hung_worker_is_killed_at_the_deadline_and_replaced() {
    let acts = actions(4, 8, 3);
    let mut env = PythonEnv::start(spec("PickCube-v1", json!({})), 5).unwrap();
    env.set_call_deadline(std::time::Duration::from_secs(3));
    env.reset_to_seed(Some(2), &json!({})).unwrap();
    env.step(&acts[0]).unwrap();
    let pid = env.worker_pid().unwrap();
    // A stopped process never answers: it stands for a simulator stuck in a loop.
    signal(pid, Signal::STOP);
    for a in &acts[1..] {
        assert_eq!(env.step(a).unwrap().obs.len(), 42);
    }
    assert_eq!(env.restarts(), 1);
    assert_ne!(env.worker_pid(), Some(pid));
    assert!(!std::path::Path::new(&format!("/proc/{pid}")).exists());
}

#[test]
fn a_worker_with_a_frame_size_renders_through_the_bridge() {
    let mut env = PythonEnv::start(spec("PickCube-v1", json!({})).with_render_size(64), 3).unwrap();
    env.reset_to_seed(Some(3), &json!({})).unwrap();
    let first = env.render().unwrap();
    assert_eq!(
        (first.width, first.height, first.rgb.len()),
        (64, 64, 64 * 64 * 3)
    );
    assert!(
        first.rgb.chunks(3).any(|p| p != &first.rgb[..3]),
        "a frame of one colour"
    );
    for a in actions(10, env.action_dim(), 5) {
        env.step(&a).unwrap();
    }
    assert_ne!(env.render().unwrap().rgb, first.rgb, "the arm moved");
    // The frames encode as a video.
    let gif = rfcl_actor::video::encode_gif(&[first.clone(), first]).unwrap();
    assert_eq!(&gif[..6], b"GIF89a");

    let mut plain = PythonEnv::start(spec("PickCube-v1", json!({})), 3).unwrap();
    let err = plain.render().unwrap_err();
    assert!(
        matches!(&err, EnvError::NoRenderer { hint } if hint.contains("render_size")),
        "{err:?}"
    );
}

#[test]
fn python_exceptions_carry_their_traceback() {
    // At start-up: the simulator's constructor refuses a keyword.
    let err = PythonEnv::start(
        spec("PickCube-v1", json!({"env_kwargs": {"no_such_kwarg": 1}})),
        0,
    )
    .err()
    .unwrap();
    let msg = err.to_string();
    assert!(
        matches!(
            err,
            PythonEnvError::Crashed { .. } | PythonEnvError::Python { .. }
        ),
        "{err:?}"
    );
    assert!(
        msg.contains("Traceback (most recent call last)") && msg.contains("no_such_kwarg"),
        "{msg}"
    );
    // An adapter's own check: bad input, named.
    let err = PythonEnv::start(spec("NoSuchCube-v1", json!({})), 0)
        .err()
        .unwrap();
    assert!(
        err.to_string()
            .contains("ManiSkill3 has no env 'NoSuchCube-v1'"),
        "{err}"
    );

    // During a reset: ManiSkill fails on reset options it cannot index with.
    let mut env = PythonEnv::start(spec("PickCube-v1", json!({})), 0).unwrap();
    let err = env
        .reset_to_seed(Some(1), &json!({"env_idx": "bogus"}))
        .unwrap_err();
    let EnvError::Simulator { message } = &err else {
        panic!("expected a simulator error, got {err:?}");
    };
    assert!(
        message.contains("Traceback (most recent call last)")
            && message.contains("sapien_env.py")
            && message.contains("IndexError"),
        "{message}"
    );
    // The worker lives on.
    env.reset_to_seed(Some(1), &json!({})).unwrap();
    assert_eq!(env.restarts(), 0);
    // Input the Rust side can check never reaches Python.
    assert_eq!(
        env.step(&[0.0; 3]).unwrap_err(),
        EnvError::ActionDim {
            expected: 8,
            got: 3
        }
    );
}
