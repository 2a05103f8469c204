//! The end of a session: `RUN_DIR/summary.json` from the curriculum's final state, the
//! evaluations and the learner's own final counters, and the line that says how the run ended.
use std::path::Path;

use anyhow::{bail, Result};
use rfcl_core::config::RunConfig;
use rfcl_core::final_counters::{FinalCounters, FINAL_COUNTERS_FILE};
use rfcl_core::run_state::RunState;

use super::progress::{
    summarize, CountersSource, Ending, EvalTracker, LearnerCounters, RunProgress, RunShape, Summary,
};
use super::write_json;

/// The counters the learner with `pid` wrote when it stopped cleanly
/// ([`FINAL_COUNTERS_FILE`]); `None` when it wrote none (killed) or the file is an earlier
/// process's.
pub fn read_final_counters(run_dir: &Path, pid: u32) -> Option<LearnerCounters> {
    let path = run_dir.join(FINAL_COUNTERS_FILE);
    let last: FinalCounters = serde_json::from_slice(&std::fs::read(&path).ok()?)
        .inspect_err(|e| tracing::warn!("reading {}: {e}", path.display()))
        .ok()?;
    (last.pid == pid).then_some(LearnerCounters {
        source: CountersSource::Final,
        counts: last.counts,
    })
}

/// What the session knew when its children had stopped.
pub struct Outcome<'a> {
    pub cfg: &'a RunConfig,
    pub run_dir: &'a Path,
    /// The curriculum's last state; `None` if it never answered.
    pub view: Option<&'a RunState>,
    pub evals: &'a EvalTracker,
    pub counters: LearnerCounters,
    pub progress: &'a RunProgress,
    pub wall_s: f64,
}

/// Writes `RUN_DIR/summary.json` (also for a failed run: `ending: failed` with its error) and
/// prints it with the line that says how the run ended. A failure comes back as the error, with
/// where its summary is.
pub fn write_summary(outcome: Outcome<'_>, ending: Result<Ending>) -> Result<Summary> {
    let summary_path = outcome.run_dir.join("summary.json");
    let Some(view) = outcome.view else {
        ending?;
        bail!("the curriculum server never answered GetState: no summary");
    };
    let (ending, failure) = match ending {
        Ok(ending) => (ending, None),
        Err(e) => (Ending::Failed, Some(e)),
    };
    let cfg = outcome.cfg;
    let shape = RunShape {
        train_envs: u64::from(cfg.env.num_envs),
        horizon: u64::from(cfg.env.max_episode_steps),
        batch_records: u64::from(cfg.service.transition_batch),
    };
    let mut summary = summarize(
        view,
        outcome.evals,
        outcome.counters,
        outcome.progress,
        shape,
        outcome.wall_s,
        ending,
    );
    if let Some(e) = failure {
        summary.error = Some(format!("{e:#}"));
        write_json(&summary_path, &summary)?;
        return Err(e.context(format!(
            "the run failed (its summary is in {})",
            summary_path.display()
        )));
    }
    write_json(&summary_path, &summary)?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    eprintln!("{}", ending_line(ending, outcome.run_dir));
    Ok(summary)
}

/// How a run that did not fail ended, and what to do next.
pub fn ending_line(ending: Ending, run_dir: &Path) -> String {
    let why = match ending {
        Ending::Interrupted => {
            return format!(
                "interrupted: continue with `rfcl train --resume {}`",
                run_dir.display()
            )
        }
        Ending::Failed => "failed",
        Ending::Budget => "step budget used",
        Ending::Stage1Done => "stage 1 ended under train.stage_1_only",
        Ending::EvalSuccess => "eval success reached",
    };
    format!(
        "run finished ({why}); summary in {}",
        run_dir.join("summary.json").display()
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use rfcl_core::final_counters::LearnerCounts;

    #[test]
    fn the_ending_line_says_why_and_what_next() {
        let dir = Path::new("runs/x");
        assert_eq!(
            ending_line(Ending::Interrupted, dir),
            "interrupted: continue with `rfcl train --resume runs/x`"
        );
        for (ending, why) in [
            (Ending::Budget, "step budget used"),
            (Ending::Stage1Done, "stage 1 ended under train.stage_1_only"),
            (Ending::EvalSuccess, "eval success reached"),
        ] {
            assert_eq!(
                ending_line(ending, dir),
                format!("run finished ({why}); summary in runs/x/summary.json")
            );
        }
    }

    #[test]
    fn final_counters_are_taken_only_from_the_learner_that_wrote_them() {
        let dir = tempfile::tempdir().unwrap();
        assert!(read_final_counters(dir.path(), 42).is_none(), "no file");
        let counts = LearnerCounts {
            env_steps: 1_000,
            updates: 250,
            ..LearnerCounts::default()
        };
        let file = FinalCounters { pid: 42, counts };
        std::fs::write(
            dir.path().join(FINAL_COUNTERS_FILE),
            serde_json::to_vec(&file).unwrap(),
        )
        .unwrap();
        let read = read_final_counters(dir.path(), 42).unwrap();
        assert_eq!((read.source, read.counts), (CountersSource::Final, counts));
        // An earlier learner's file says nothing of this one.
        assert!(read_final_counters(dir.path(), 43).is_none());
    }
}
