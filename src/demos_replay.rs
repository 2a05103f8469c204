//! `rfcl demos inspect --replay`: each demo checked in its simulator, with no run
//! (rfcl_actor::replay): valid reset states, a faithful replay of its actions, a success at the end.
use std::path::Path;

use anyhow::{bail, Context, Result};
use rfcl_actor::pointmaze::{self, PointMaze};
use rfcl_actor::replay::{check_demo, STATE_TOLERANCE};
use rfcl_actor::Env;
use rfcl_core::demo::DemoSet;

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
    println!("replay check (states within {STATE_TOLERANCE} of the demo's):");
    let mut failed = 0;
    for (i, demo) in set.demos.iter().enumerate() {
        let c = check_demo(env.as_mut(), demo)
            .with_context(|| format!("replaying demo {i} (episode {})", demo.episode_id))?;
        let mut problems = Vec::new();
        if let Some((index, why)) = &c.invalid_state {
            problems.push(format!("state {index} is not a valid reset state: {why}"));
        }
        if let Some(t) = c.first_divergence {
            problems.push(format!(
                "the replay leaves the demo's states at state {t} (max error {:.3e})",
                c.max_state_error
            ));
        }
        if c.success_mismatches > 0 {
            problems.push(format!(
                "{} success flags differ from the replay's",
                c.success_mismatches
            ));
        }
        if c.invalid_state.is_none() && !c.final_success {
            problems.push("its final state is not a success".into());
        }
        if problems.is_empty() {
            println!(
                "  demo {i} (episode {}): ok ({} steps, max state error {:.1e}, success at the end)",
                demo.episode_id,
                demo.len(),
                c.max_state_error
            );
        } else {
            failed += 1;
            println!(
                "  demo {i} (episode {}): FAILED: {}",
                demo.episode_id,
                problems.join("; ")
            );
        }
    }
    println!(
        "{} of {} demos pass the replay check",
        set.demos.len() - failed,
        set.demos.len()
    );
    Ok(failed == 0)
}
