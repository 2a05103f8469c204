//! From a run's env config to env instances: the one place that knows which suites an actor can
//! run. PointMaze runs natively (spec 7.5); ManiSkill3, MetaWorld and Adroit (spec 7.1-7.4) run
//! in Python worker processes ([`crate::python`]), whose adapters report their own dims.
use rfcl_core::config::{EnvConfig, Suite};
use rfcl_core::demo::{DemoSet, StateLayout};

use crate::env::Env;
use crate::pointmaze::{self, PointMaze};
use crate::python::{self, PythonEnv, WorkerSpec};

/// Why no env could be made for a run.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SuiteError {
    #[error(
        "suite pointmaze has one env, '{}'; the run asks for '{env_id}'",
        pointmaze::ENV_ID
    )]
    UnknownPointMaze { env_id: String },
    #[error("the run expects {what} {expected}, but env '{env_id}' has {got}")]
    Dim {
        env_id: String,
        what: &'static str,
        expected: usize,
        got: usize,
    },
    /// The demo file's observations, actions or states do not fit the env.
    #[error("the demos do not fit env '{env_id}' of suite '{suite}': {why}")]
    DemosDoNotFit {
        suite: String,
        env_id: String,
        why: String,
    },
    /// The Python worker could not be found, started or asked (the message says which, with the
    /// Python traceback where there is one).
    #[error("env '{env_id}' of suite '{suite}': {message}")]
    Python {
        suite: String,
        env_id: String,
        message: String,
    },
}

/// Whether this actor can make envs of `env`'s suite, without starting one: PointMaze's env id,
/// and for the Python suites that the worker binary is there (the dims are checked by
/// [`make_env`]).
pub fn check_supported(env: &EnvConfig) -> Result<(), SuiteError> {
    match env.suite {
        Suite::Pointmaze if env.env_id != pointmaze::ENV_ID => Err(SuiteError::UnknownPointMaze {
            env_id: env.env_id.clone(),
        }),
        Suite::Pointmaze => Ok(()),
        _ => WorkerSpec::from_env_config(env)
            .map(|_| ())
            .map_err(|e| python_error(env, e)),
    }
}

/// The observation and action dims of `env`'s envs (for a Python suite, from a worker started and
/// stopped for the purpose).
pub fn native_dims(env: &EnvConfig) -> Result<(usize, usize), SuiteError> {
    check_supported(env)?;
    match env.suite {
        Suite::Pointmaze => Ok((pointmaze::OBS_DIM, pointmaze::ACTION_DIM)),
        _ => {
            let spec = WorkerSpec::from_env_config(env).map_err(|e| python_error(env, e))?;
            let hello = python::describe(&spec).map_err(|e| python_error(env, e))?;
            Ok((hello.obs_dim, hello.action_dim))
        }
    }
}

/// Whether the demos of `set` fit `env`: the same observation and action dims and the same state
/// layout (names, kinds and lengths, in order), so that every demo state is one the env can
/// restore; for PointMaze (native and cheap) every state of every demo is also tried as a reset
/// state, so that a bad one is refused here rather than at an actor's first lease on it. For a
/// Python suite a worker is started and stopped to ask the env. What `rfcl train` checks.
pub fn check_demos_fit(env: &EnvConfig, set: &DemoSet) -> Result<(), SuiteError> {
    check_fit(env, set, env.suite == Suite::Pointmaze)
}

/// [`check_demos_fit`], and every state of every demo tried as a reset state (after its demo's
/// seed and options) in the env's own simulator, whatever its suite: one reset per state, which
/// for a Python suite can take a minute (PegInsertionSide-v1 rebuilds its scene at each, ~170 ms).
/// What `rfcl demos inspect --config` checks.
pub fn check_demo_states(env: &EnvConfig, set: &DemoSet) -> Result<(), SuiteError> {
    check_fit(env, set, true)
}

fn check_fit(env: &EnvConfig, set: &DemoSet, try_states: bool) -> Result<(), SuiteError> {
    check_supported(env)?;
    let refuse = |why: String| SuiteError::DemosDoNotFit {
        suite: python::suite_name(env.suite),
        env_id: env.env_id.clone(),
        why,
    };
    let (made, layout): (Option<Box<dyn Env>>, _) = match env.suite {
        Suite::Pointmaze => (
            Some(Box::new(PointMaze::new(0))),
            (
                pointmaze::OBS_DIM,
                pointmaze::ACTION_DIM,
                pointmaze::state_layout(),
            ),
        ),
        _ => {
            let spec = WorkerSpec::from_env_config(env).map_err(|e| python_error(env, e))?;
            if try_states {
                let made = PythonEnv::start(spec, 0).map_err(|e| python_error(env, e))?;
                let layout = (
                    made.obs_dim(),
                    made.action_dim(),
                    made.state_layout().clone(),
                );
                (Some(Box::new(made)), layout)
            } else {
                let layout = python::describe_layout(&spec).map_err(|e| python_error(env, e))?;
                (None, layout)
            }
        }
    };
    let (obs_dim, action_dim, layout) = layout;
    demos_fit(
        (obs_dim, action_dim, &layout),
        (set.obs_dim, set.action_dim, &set.state_layout),
    )
    .map_err(refuse)?;
    let Some(mut made) = made.filter(|_| try_states) else {
        return Ok(());
    };
    match crate::replay::first_refused_state(made.as_mut(), &set.demos) {
        None => Ok(()),
        Some((demo, episode, t, why)) => Err(refuse(format!(
            "demo {demo} (episode {episode}) state {t} is not a valid reset state: {why}"
        ))),
    }
}

/// The first way demos of (obs dim, action dim, state layout) `demos` differ from an env's.
pub fn demos_fit(
    env: (usize, usize, &StateLayout),
    demos: (usize, usize, &StateLayout),
) -> Result<(), String> {
    let (env_obs, env_action, env_layout) = env;
    let (obs, action, layout) = demos;
    if (obs, action) != (env_obs, env_action) {
        return Err(format!(
            "the demos have obs {obs} and action {action} values, the env {env_obs} and \
             {env_action}"
        ));
    }
    if layout != env_layout {
        return Err(format!(
            "the demos' states are {} ({} values), the env's {} ({} values)",
            layout.describe(),
            layout.dim(),
            env_layout.describe(),
            env_layout.dim()
        ));
    }
    Ok(())
}

fn python_error(env: &EnvConfig, e: python::PythonEnvError) -> SuiteError {
    SuiteError::Python {
        suite: python::suite_name(env.suite),
        env_id: env.env_id.clone(),
        message: e.to_string(),
    }
}

/// A new env for `env` whose RNG starts from `seed` (see [`crate::rollout::derive_seed`]), checked
/// against the dims the run expects (`expected_obs_dim`, `expected_action_dim`: from the learner's
/// run description, which come from the demos). With `render_size`, a Python simulator renders
/// square frames of that many pixels ([`Env::render`]); PointMaze always renders, at its own size.
pub fn make_env(
    env: &EnvConfig,
    seed: u64,
    expected_obs_dim: usize,
    expected_action_dim: usize,
    render_size: Option<u32>,
) -> Result<Box<dyn Env>, SuiteError> {
    check_supported(env)?;
    let made: Box<dyn Env> = match env.suite {
        Suite::Pointmaze => Box::new(PointMaze::new(seed)),
        _ => {
            let mut spec = WorkerSpec::from_env_config(env).map_err(|e| python_error(env, e))?;
            if let Some(side) = render_size {
                spec = spec.with_render_size(side);
            }
            Box::new(PythonEnv::start(spec, seed).map_err(|e| python_error(env, e))?)
        }
    };
    for (what, expected, got) in [
        ("obs_dim", expected_obs_dim, made.obs_dim()),
        ("action_dim", expected_action_dim, made.action_dim()),
    ] {
        if expected != got {
            return Err(SuiteError::Dim {
                env_id: env.env_id.clone(),
                what,
                expected,
                got,
            });
        }
    }
    Ok(made)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pointmaze_is_made_and_checked() {
        let cfg = EnvConfig::default();
        assert_eq!(native_dims(&cfg), Ok((7, 2)));
        let env = make_env(&cfg, 3, 7, 2, None).unwrap();
        assert_eq!(
            (env.obs_dim(), env.action_dim(), env.horizon()),
            (7, 2, 300)
        );
        let err = make_env(&cfg, 3, 8, 2, None).err().unwrap();
        assert_eq!(
            err.to_string(),
            "the run expects obs_dim 8, but env 'PointMaze-v0' has 7"
        );
        let mut wrong = cfg.clone();
        wrong.env_id = "PointMaze-Large".into();
        assert!(matches!(
            make_env(&wrong, 3, 7, 2, None).err().unwrap(),
            SuiteError::UnknownPointMaze { .. }
        ));
    }

    #[test]
    fn demos_fit_only_an_env_of_their_dims_and_state_layout() {
        use rfcl_core::demo::StateKind;
        let fields = |parts: &[(&str, usize)]| {
            StateLayout::from_parts(
                parts
                    .iter()
                    .map(|&(n, len)| (n.to_owned(), StateKind::Field, len)),
            )
        };
        let env = fields(&[("pos", 2), ("vel", 2)]);
        assert_eq!(demos_fit((6, 2, &env), (6, 2, &env.clone())), Ok(()));
        assert_eq!(
            demos_fit((6, 2, &env), (7, 2, &env)).unwrap_err(),
            "the demos have obs 7 and action 2 values, the env 6 and 2"
        );
        let renamed = fields(&[("position", 2), ("vel", 2)]);
        assert_eq!(
            demos_fit((6, 2, &env), (6, 2, &renamed)).unwrap_err(),
            "the demos' states are position (2), vel (2) (4 values), the env's pos (2), vel (2) \
             (4 values)"
        );
        // PointMaze's own demos fit it; one with a collision flag of 50 in a state is refused,
        // naming the demo, the state and the field.
        let mut set = crate::pointmaze::demos::demo_set(
            crate::pointmaze::demos::generate_demos(2, 0),
            "x.h5",
        );
        assert_eq!(check_demos_fit(&EnvConfig::default(), &set), Ok(()));
        let dim = set.state_dim;
        set.demos[1].env_states[7 * dim + dim - 1] = 50.0;
        let err = check_demos_fit(&EnvConfig::default(), &set)
            .unwrap_err()
            .to_string();
        let expected = format!(
            "demo 1 (episode {}) state 7 is not a valid reset state: ",
            set.demos[1].episode_id
        );
        assert!(
            err.contains(&expected)
                && err.contains("collided")
                && err.contains("50 is neither 0 nor 1"),
            "{err}"
        );
    }

    #[test]
    fn python_suites_without_a_worker_binary_say_how_to_build_it() {
        let cfg = EnvConfig {
            env_id: "PickCube-v1".into(),
            suite: Suite::Maniskill3,
            ..EnvConfig::default()
        };
        match check_supported(&cfg) {
            // A built worker next to the test binary is fine too.
            Ok(()) => {}
            Err(err) => {
                let msg = err.to_string();
                assert!(
                    msg.contains("'PickCube-v1'")
                        && msg.contains("suite 'maniskill3'")
                        && msg.contains("rfcl-sim-worker"),
                    "{msg}"
                );
            }
        }
    }
}
