//! When eval actors evaluate and how much (spec 5.7), as pure logic.
//!
//! An eval actor watches the policies the learner publishes. Each time the learner's env-step count
//! passes a multiple of `sac.eval_freq` — and only once it exceeds the seed steps — it runs
//! [`episodes_per_eval`] EVAL-lease episodes with the deterministic policy of that moment and
//! reports them; the curriculum server aggregates them per policy version, keyed by the env steps
//! at publication, so every curve is exact. A (re)started eval actor goes on after the newest
//! complete evaluation the curriculum server has, so a resumed run evaluates no point twice.
use rfcl_core::config::RunConfig;

pub use rfcl_core::config::episodes_per_eval;
use rfcl_core::config::eval_point;

/// This eval actor's share of an evaluation when `num_eval_actors` share it (rounded up, so the
/// evaluation is never short).
pub fn episodes_per_eval_actor(cfg: &RunConfig) -> u64 {
    episodes_per_eval(cfg).div_ceil(u64::from(cfg.service.num_eval_actors.max(1)))
}

/// Decides, per published policy, whether an evaluation is due (spec 5.7).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EvalSchedule {
    eval_freq: u64,
    num_seed_steps: u64,
    /// Multiples of `eval_freq` passed by the last evaluated policy.
    done_through: u64,
    /// Due evaluations that were skipped because the learner passed several multiples of
    /// `eval_freq` during one evaluation (counted, never silent).
    skipped: u64,
}

impl EvalSchedule {
    pub fn new(eval_freq: u64, num_seed_steps: u64) -> Self {
        Self {
            eval_freq: eval_freq.max(1),
            num_seed_steps,
            done_through: 0,
            skipped: 0,
        }
    }

    pub fn from_config(cfg: &RunConfig) -> Self {
        Self::new(cfg.sac.eval_freq, cfg.sac.num_seed_steps)
    }

    /// Goes on after the evaluations already complete, the newest of a policy published at
    /// `env_steps` (0: none): the next one is due past the next multiple of `eval_freq`.
    pub fn go_on_after(&mut self, env_steps: u64) {
        self.done_through = self.done_through.max(env_steps / self.eval_freq);
    }

    /// Whether the policy published at `learner_env_steps` is to be evaluated. Marks it evaluated
    /// when it is; evaluation points passed over (more than one multiple of `eval_freq` since the
    /// last evaluation) are counted in [`EvalSchedule::skipped`].
    pub fn due(&mut self, learner_env_steps: u64) -> bool {
        let Some(through) = eval_point(learner_env_steps, self.eval_freq, self.num_seed_steps)
        else {
            return false;
        };
        if through <= self.done_through {
            return false;
        }
        // The first evaluation after a (re)start has nothing before it to skip.
        if self.done_through > 0 {
            self.skipped += through - self.done_through - 1;
        }
        self.done_through = through;
        true
    }

    pub fn skipped(&self) -> u64 {
        self.skipped
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evaluates_once_per_multiple_of_eval_freq_after_the_seed_steps() {
        let mut s = EvalSchedule::new(1000, 1500);
        assert!(!s.due(0));
        assert!(!s.due(1200), "1000 passed, but not the seed steps");
        assert!(s.due(1532));
        assert!(!s.due(1900));
        assert!(s.due(2000));
        assert!(!s.due(2000));
        assert!(!s.due(2999));
        assert!(s.due(3010));
        assert_eq!(s.skipped(), 0);
        // The learner ran past two more points during an evaluation: one is evaluated, one skipped.
        assert!(s.due(5001));
        assert_eq!(s.skipped(), 1);
    }

    #[test]
    fn a_restarted_eval_actor_evaluates_the_first_policy_past_a_multiple() {
        let mut s = EvalSchedule::new(1000, 100);
        assert!(s.due(45_500));
        assert_eq!(s.skipped(), 0);
        assert!(!s.due(45_900));
    }

    #[test]
    fn a_resumed_run_evaluates_no_point_twice() {
        // Stopped at 176,224 env steps after the evaluation at 160,008: the restored policy is
        // not evaluated (it is still within the point 160,000), the first past 180,000 is.
        let mut s = EvalSchedule::new(20_000, 5_000);
        s.go_on_after(160_008);
        assert!(!s.due(176_224));
        assert!(s.due(180_032));
        assert_eq!(s.skipped(), 0);
        // Stopped during the evaluation at 180,032 (incomplete): the restored policy stands in.
        let mut s = EvalSchedule::new(20_000, 5_000);
        s.go_on_after(160_008);
        assert!(s.due(181_000));
        // No evaluation yet: as a fresh start.
        let mut s = EvalSchedule::new(20_000, 5_000);
        s.go_on_after(0);
        assert!(s.due(20_008));
    }

    #[test]
    fn episode_counts_follow_the_eval_env() {
        let mut cfg = RunConfig::default();
        cfg.env.max_episode_steps = 300;
        cfg.eval_env.num_envs = 4;
        cfg.sac.eval_steps = 1000;
        // 4 × 1000 / 300 = 13.
        assert_eq!(episodes_per_eval(&cfg), 13);
        cfg.eval_env.num_envs = 2;
        cfg.eval_env.max_episode_steps = Some(500);
        // 2 × 1000 / 500 = 4, raised to 10.
        assert_eq!(episodes_per_eval(&cfg), 10);
        cfg.eval_env.num_envs = 4;
        cfg.eval_env.max_episode_steps = None;
        cfg.sac.eval_steps = 2550;
        assert_eq!(episodes_per_eval(&cfg), 34);
        cfg.service.num_eval_actors = 3;
        assert_eq!(episodes_per_eval_actor(&cfg), 12);
    }
}
