//! From a run's env config to env instances: the one place that knows which suites an actor can
//! run. PointMaze runs natively (spec 7.5); the simulator suites (ManiSkill3, MetaWorld, Adroit,
//! spec 7.1-7.4) need Python workers that this actor does not drive yet, and say so.
use rfcl_core::config::{EnvConfig, Suite};

use crate::env::Env;
use crate::pointmaze::{self, PointMaze};

/// Why no env could be made for a run.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SuiteError {
    #[error(
        "env '{env_id}' of suite '{suite}' is not supported by the actor yet: only PointMaze \
         ({}) runs natively; the Python simulator workers come with later issues",
        pointmaze::ENV_ID
    )]
    Unsupported { suite: String, env_id: String },
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
}

/// Whether this actor can make envs of `env`'s suite (the dims are checked by [`make_env`]).
pub fn check_supported(env: &EnvConfig) -> Result<(), SuiteError> {
    match env.suite {
        Suite::Pointmaze if env.env_id != pointmaze::ENV_ID => Err(SuiteError::UnknownPointMaze {
            env_id: env.env_id.clone(),
        }),
        Suite::Pointmaze => Ok(()),
        other => Err(SuiteError::Unsupported {
            suite: suite_name(other),
            env_id: env.env_id.clone(),
        }),
    }
}

/// The observation and action dims of `env`'s envs.
pub fn native_dims(env: &EnvConfig) -> Result<(usize, usize), SuiteError> {
    // PointMaze is the one suite `check_supported` accepts.
    check_supported(env)?;
    Ok((pointmaze::OBS_DIM, pointmaze::ACTION_DIM))
}

fn suite_name(suite: Suite) -> String {
    serde_json::to_value(suite)
        .ok()
        .and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_else(|| format!("{suite:?}"))
}

/// A new env for `env` whose RNG starts from `seed` (see [`crate::rollout::derive_seed`]), checked
/// against the dims the run expects (`expected_obs_dim`, `expected_action_dim`: from the learner's
/// run description, which come from the demos).
pub fn make_env(
    env: &EnvConfig,
    seed: u64,
    expected_obs_dim: usize,
    expected_action_dim: usize,
) -> Result<Box<dyn Env>, SuiteError> {
    // PointMaze is the one suite `check_supported` accepts.
    check_supported(env)?;
    let made: Box<dyn Env> = Box::new(PointMaze::new(seed));
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
        let env = make_env(&cfg, 3, 7, 2).unwrap();
        assert_eq!(
            (env.obs_dim(), env.action_dim(), env.horizon()),
            (7, 2, 300)
        );
        let err = make_env(&cfg, 3, 8, 2).err().unwrap();
        assert_eq!(
            err.to_string(),
            "the run expects obs_dim 8, but env 'PointMaze-v0' has 7"
        );
        let mut wrong = cfg.clone();
        wrong.env_id = "PointMaze-Large".into();
        assert!(matches!(
            make_env(&wrong, 3, 7, 2).err().unwrap(),
            SuiteError::UnknownPointMaze { .. }
        ));
    }

    #[test]
    fn simulator_suites_say_not_supported_yet() {
        let cfg = EnvConfig {
            env_id: "PickCube-v1".into(),
            suite: Suite::Maniskill3,
            ..EnvConfig::default()
        };
        assert_eq!(check_supported(&cfg).err(), make_env(&cfg, 0, 42, 8).err());
        let err = make_env(&cfg, 0, 42, 8).err().unwrap();
        let msg = err.to_string();
        assert!(
            msg.contains("'PickCube-v1'")
                && msg.contains("suite 'maniskill3'")
                && msg.contains("not supported by the actor yet"),
            "{msg}"
        );
    }
}
