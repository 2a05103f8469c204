//! What `rfcl train` shows while it runs: the progress bar on a terminal (a status line every
//! 15 s elsewhere: logs, tests) and the lines it prints about evaluations and the children. The
//! texts are pure functions, tested here; [`Bar`] only writes them.
use std::io::IsTerminal;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressStyle};

use super::policy::SilenceAction;
use super::progress::CompleteEval;

/// The bar's message: `stage 1 | eval 40% | 31.5 upd/s`.
pub fn status(stage: u32, last_eval: Option<&CompleteEval>, updates_per_s: f64) -> String {
    let eval = last_eval.map_or("-".to_string(), |e| {
        format!("{:.0}%", 100.0 * e.point.success_at_end)
    });
    format!("stage {stage} | eval {eval} | {updates_per_s:.1} upd/s")
}

/// The line printed when an evaluation completes.
pub fn eval_line(e: &CompleteEval) -> String {
    let p = &e.point;
    format!(
        "eval at {} env steps (policy v{}): success {:.0}% at the end, {:.0}% once, mean return \
         {:.1} ({} episodes)",
        p.env_steps,
        p.policy_version,
        100.0 * p.success_at_end,
        100.0 * p.success_once,
        p.mean_return,
        p.episodes
    )
}

/// What is said of a service that has not answered (`name`, `pid`), if anything;
/// `timeout_s` is `service.hang_timeout_s`.
pub fn silence_line(
    name: &str,
    pid: u32,
    action: SilenceAction,
    timeout_s: Option<f64>,
) -> Option<String> {
    match action {
        SilenceAction::Wait => None,
        SilenceAction::Warn(s) => Some(match timeout_s {
            Some(t) => format!(
                "the {name} (pid {pid}) has not answered for {s:.0} s; it is restarted if it \
                 stays silent for {t:.0} s (service.hang_timeout_s)"
            ),
            None => format!("the {name} (pid {pid}) has not answered for {s:.0} s"),
        }),
        SilenceAction::Kill(s) => Some(format!(
            "the {name} (pid {pid}) has not answered for {s:.0} s: killing it to restart it"
        )),
    }
}

/// The progress bar on a terminal; a status line every 15 s elsewhere (logs, tests).
pub struct Bar {
    bar: Option<ProgressBar>,
    total: u64,
    last_line: std::cell::Cell<Option<Instant>>,
}

impl Bar {
    pub fn new(total: u64) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::new(total);
            bar.set_style(
                ProgressStyle::with_template(
                    "{bar:30.cyan/blue} {human_pos}/{human_len} env steps | {msg} | \
                     {elapsed_precise} elapsed, ETA {eta}",
                )
                .expect("a valid template"),
            );
            bar
        });
        Self {
            bar,
            total,
            last_line: std::cell::Cell::new(None),
        }
    }

    pub fn update(&self, env_steps: u64, msg: String) {
        match &self.bar {
            Some(bar) => {
                bar.set_position(env_steps.min(self.total));
                bar.set_message(msg);
            }
            None => {
                let due = self
                    .last_line
                    .get()
                    .is_none_or(|t| t.elapsed() >= Duration::from_secs(15));
                if due {
                    self.last_line.set(Some(Instant::now()));
                    eprintln!("{env_steps}/{} env steps | {msg}", self.total);
                }
            }
        }
    }

    pub fn println(&self, line: impl AsRef<str>) {
        match &self.bar {
            Some(bar) => bar.println(line.as_ref()),
            None => eprintln!("{}", line.as_ref()),
        }
    }

    pub fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rfcl_core::run_state::EvalPoint;

    fn eval(success: f64) -> CompleteEval {
        CompleteEval {
            point: EvalPoint {
                policy_version: 12,
                env_steps: 40_000,
                episodes: 50,
                success_at_end: success,
                success_once: 0.5,
                mean_return: 3.26,
            },
            wall_s: 100.0,
        }
    }

    #[test]
    fn the_status_says_stage_last_eval_and_update_rate() {
        assert_eq!(status(1, None, 0.0), "stage 1 | eval - | 0.0 upd/s");
        assert_eq!(
            status(2, Some(&eval(0.4)), 31.46),
            "stage 2 | eval 40% | 31.5 upd/s"
        );
        assert_eq!(
            eval_line(&eval(0.4)),
            "eval at 40000 env steps (policy v12): success 40% at the end, 50% once, mean return \
             3.3 (50 episodes)"
        );
    }

    #[test]
    fn a_silent_service_is_warned_about_then_killed() {
        assert_eq!(
            silence_line("learner", 7, SilenceAction::Wait, Some(60.0)),
            None
        );
        assert_eq!(
            silence_line("learner", 7, SilenceAction::Warn(15.2), Some(60.0)).unwrap(),
            "the learner (pid 7) has not answered for 15 s; it is restarted if it stays silent \
             for 60 s (service.hang_timeout_s)"
        );
        assert_eq!(
            silence_line("learner", 7, SilenceAction::Warn(15.2), None).unwrap(),
            "the learner (pid 7) has not answered for 15 s"
        );
        assert_eq!(
            silence_line(
                "curriculum-server",
                9,
                SilenceAction::Kill(60.0),
                Some(60.0)
            )
            .unwrap(),
            "the curriculum-server (pid 9) has not answered for 60 s: killing it to restart it"
        );
    }
}
