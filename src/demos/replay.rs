//! `rfcl demos inspect --replay`: each demo checked in its simulator, with no run
//! (rfcl_actor::replay): states that restore exactly, steps that replay, a success at the end.
use std::path::Path;

use anyhow::{bail, Context, Result};
use rfcl_actor::pointmaze::{self, PointMaze};
use rfcl_actor::replay::{
    check_demo, verdict, ORIENTATION_TOLERANCE, POSITION_TOLERANCE, RESTORE_TOLERANCE,
};
use rfcl_actor::Env;
use rfcl_core::demo::DemoSet;

/// Without `--replay`: every state of every demo tried as a reset state in the env `config`
/// describes (PointMaze needs none), after the dims and state layout are found to fit, and the
/// first refused one named; true when all are valid. A Python-suite file without `config` is
/// not checked, and says so.
pub fn reset_states(set: &DemoSet, config: Option<&Path>) -> Result<bool> {
    let env = match (config, set.env_id.as_deref()) {
        (Some(path), _) => rfcl_core::config::resolve_file(path, &[])?.env,
        (None, Some(pointmaze::ENV_ID)) => rfcl_core::config::EnvConfig::default(),
        (None, _) => {
            println!(
                "reset states not checked: pass --config CFG, the run config whose env takes \
                 them, to try each in its simulator"
            );
            return Ok(true);
        }
    };
    match rfcl_actor::suite::check_demo_states(&env, set) {
        Ok(()) => {
            println!("every state of every demo is a valid reset state");
            Ok(true)
        }
        Err(e @ rfcl_actor::suite::SuiteError::DemosDoNotFit { .. }) => {
            println!("{e}");
            Ok(false)
        }
        Err(e) => Err(e).context("making the env to try the demo states in"),
    }
}

/// Checks every demo of `set`, printing one line each; true when all pass. The env is PointMaze
/// for PointMaze files, else the one `config` describes.
pub fn check(set: &DemoSet, config: Option<&Path>) -> Result<bool> {
    let mut env: Box<dyn Env> = match (config, set.env_id.as_deref()) {
        (Some(path), _) => {
            let cfg = rfcl_core::config::resolve_file(path, &[])?;
            rfcl_actor::suite::make_env(&cfg.env, 0, set.obs_dim, set.action_dim, None)
                .with_context(|| format!("making the env of {}", path.display()))?
        }
        (None, Some(pointmaze::ENV_ID)) => Box::new(PointMaze::new(0)),
        (None, env_id) => bail!(
            "--replay of {} (env {}) needs --config CFG: the run config whose env replays it",
            set.path.display(),
            env_id.unwrap_or("unknown")
        ),
    };
    println!(
        "replay check: every state restores within {RESTORE_TOLERANCE:e}; one step from each \
         state reaches the next with positions within {POSITION_TOLERANCE} and orientations within \
         {ORIENTATION_TOLERANCE} rad (velocities reported, not judged) and its success flag; the \
         last step ends in a success"
    );
    let mut failed = 0;
    for (i, demo) in set.demos.iter().enumerate() {
        let c = check_demo(env.as_mut(), demo)
            .with_context(|| format!("replaying demo {i} (episode {})", demo.episode_id))?;
        match verdict(&c, demo.len() + 1) {
            Ok(measured) => println!(
                "  demo {i} (episode {}): ok ({} steps; {measured})",
                demo.episode_id,
                demo.len(),
            ),
            Err(problems) => {
                failed += 1;
                println!(
                    "  demo {i} (episode {}): FAILED: {problems}",
                    demo.episode_id
                );
            }
        }
    }
    println!(
        "{} of {} demos pass the replay check",
        set.demos.len() - failed,
        set.demos.len()
    );
    Ok(failed == 0)
}
