//! The update-to-data (UTD) limiter: when the learner may run a training iteration, given the env
//! steps it has received (spec 5.2, 5.4, 4.4; docs/LEARNER.md). Pure bookkeeping: no
//! clock, no I/O.
//!
//! Let K = `env.num_envs · sac.steps_per_env` (env steps per iteration of the reference loop) and
//! W the phase's warm-up (`sac.num_seed_steps`). A *phase* starts at the start of the run (stage 1,
//! or stage 2 with `stage_2_only`) and again at the stage transition (spec 4.4: the next W steps are
//! policy-only, with no updates). With n the env steps received in the current phase, the
//! reference runs one iteration after every K steps whose count *before* the increment is ≥ W
//! (spec 5.4), so by n it has run
//!
//! ```text
//! earned(n) = max(0, ⌊n / K⌋ − ⌈W / K⌉)
//! ```
//!
//! iterations in the phase.
//!
//! * `sync`: the learner runs exactly `earned(n)` iterations: one becomes [`due`](UtdLimiter::due)
//!   the moment the K-th step of its chunk arrives, and the ingest takes no further step until it
//!   has run ([`steps_before_due`](UtdLimiter::steps_before_due)). Critic updates per received
//!   env step are therefore G/K exactly at every iteration boundary (the 5 % bound over any window
//!   of 10 iterations holds with zero error); the ingest queue is bounded, so a slow learner
//!   holds actors back.
//! * `async`: once the first iteration is earned, the learner updates flat out and reports the
//!   achieved ratio ([`UtdLimiter::achieved_utd`]).
//!
//! After a resume or a mode change, a backlog of owed iterations is clamped to one, never run as
//! a burst ([`UtdLimiter::clamp_backlog`]); the forgiven iterations are counted.
use rfcl_core::config::UtdMode;
use serde::{Deserialize, Serialize};

/// Iterations owed beyond this are forgiven by [`UtdLimiter::clamp_backlog`].
pub const MAX_BACKLOG: u64 = 1;

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct UtdLimiter {
    mode: UtdMode,
    /// K: env steps per iteration.
    steps_per_iteration: u64,
    /// Critic updates per iteration (G), for the ratio.
    critic_updates_per_iteration: u64,
    /// Env steps received in total (every phase).
    env_steps: u64,
    /// `env_steps` when the current phase began.
    phase_start: u64,
    /// W of the current phase.
    warmup: u64,
    /// Iterations run in the current phase (including forgiven ones).
    phase_iterations: u64,
    /// Iterations run in total.
    iterations: u64,
    /// Env steps received past each phase's warm-up chunks (the steps that earn iterations), for
    /// the ratio.
    steps_while_updating: u64,
    /// Iterations forgiven by [`clamp_backlog`](Self::clamp_backlog).
    forgiven: u64,
}

impl UtdLimiter {
    /// A limiter at env step 0 whose first phase has `warmup` update-free steps.
    ///
    /// # Panics
    /// When `steps_per_iteration` is 0 (the config validation rejects it earlier).
    pub fn new(
        mode: UtdMode,
        steps_per_iteration: u64,
        critic_updates_per_iteration: u64,
        warmup: u64,
    ) -> Self {
        assert!(
            steps_per_iteration > 0,
            "K = num_envs · steps_per_env must be positive"
        );
        Self {
            mode,
            steps_per_iteration,
            critic_updates_per_iteration,
            env_steps: 0,
            phase_start: 0,
            warmup,
            phase_iterations: 0,
            iterations: 0,
            steps_while_updating: 0,
            forgiven: 0,
        }
    }

    pub fn mode(&self) -> UtdMode {
        self.mode
    }
    /// K.
    pub fn steps_per_iteration(&self) -> u64 {
        self.steps_per_iteration
    }
    pub fn env_steps(&self) -> u64 {
        self.env_steps
    }
    pub fn iterations(&self) -> u64 {
        self.iterations
    }
    pub fn forgiven(&self) -> u64 {
        self.forgiven
    }
    /// Env steps received in the current phase.
    pub fn phase_steps(&self) -> u64 {
        self.env_steps - self.phase_start
    }

    /// Iterations the schedule grants the current phase so far (module docs).
    pub fn earned(&self) -> u64 {
        let chunks = self.phase_steps() / self.steps_per_iteration;
        chunks.saturating_sub(self.warmup.div_ceil(self.steps_per_iteration))
    }

    /// Whether the warm-up of the current phase is over (the first iteration has been earned).
    pub fn updating(&self) -> bool {
        self.earned() > 0 || self.phase_iterations > 0
    }

    /// Iterations to run now before taking more data. `sync`: the earned iterations not yet
    /// run (0 or 1 in steady state). `async`: 1 whenever updates are allowed.
    pub fn due(&self) -> u64 {
        match self.mode {
            UtdMode::Sync => self.earned().saturating_sub(self.phase_iterations),
            UtdMode::Async => u64::from(self.updating()),
        }
    }

    /// `sync`: how many more env steps may be received before the next iteration is due (0 when
    /// one is due now). `async`: unlimited.
    pub fn steps_before_due(&self) -> u64 {
        match self.mode {
            UtdMode::Async => u64::MAX,
            UtdMode::Sync if self.due() > 0 => 0,
            UtdMode::Sync => {
                let k = self.steps_per_iteration;
                // The iteration after the ones run so far is earned at phase step
                // (phase_iterations + 1 + ⌈W/K⌉)·K.
                let at = (self.phase_iterations + 1 + self.warmup.div_ceil(k)) * k;
                at - self.phase_steps()
            }
        }
    }

    /// Records `n` received env steps.
    pub fn receive(&mut self, n: u64) {
        // Steps past the phase's warm-up chunks are the ones that earn iterations.
        let threshold = self.phase_start
            + self.warmup.div_ceil(self.steps_per_iteration) * self.steps_per_iteration;
        let counted_from = self.env_steps.max(threshold);
        self.env_steps += n;
        self.steps_while_updating += self.env_steps.saturating_sub(counted_from);
    }

    /// Records one finished iteration.
    pub fn iteration_done(&mut self) {
        self.phase_iterations += 1;
        self.iterations += 1;
    }

    /// Starts a new phase here with `warmup` update-free steps (the stage transition, spec 4.4).
    pub fn start_phase(&mut self, warmup: u64) {
        self.phase_start = self.env_steps;
        self.warmup = warmup;
        self.phase_iterations = 0;
    }

    /// Forgives owed iterations beyond [`MAX_BACKLOG`] (after a resume, or when a checkpoint of
    /// another mode or schedule is resumed): catch-up is clamped, never a burst. Returns how many
    /// were forgiven now.
    pub fn clamp_backlog(&mut self) -> u64 {
        let owed = self.earned().saturating_sub(self.phase_iterations);
        let forgive = owed.saturating_sub(MAX_BACKLOG);
        self.phase_iterations += forgive;
        self.forgiven += forgive;
        forgive
    }

    /// Adopts another mode and schedule (a resumed run whose config changed them), keeping the
    /// counters; the caller should [`clamp_backlog`](Self::clamp_backlog) next.
    pub fn reconfigure(&mut self, mode: UtdMode, steps_per_iteration: u64, critic_updates: u64) {
        assert!(steps_per_iteration > 0, "K must be positive");
        self.mode = mode;
        self.steps_per_iteration = steps_per_iteration;
        self.critic_updates_per_iteration = critic_updates;
    }

    /// Critic updates per env step received since updates began (the configured G/K in `sync`).
    pub fn achieved_utd(&self) -> f64 {
        if self.steps_while_updating == 0 {
            return 0.0;
        }
        (self.iterations * self.critic_updates_per_iteration) as f64
            / self.steps_while_updating as f64
    }

    /// The configured ratio G/K.
    pub fn target_utd(&self) -> f64 {
        self.critic_updates_per_iteration as f64 / self.steps_per_iteration as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Drives a limiter the way the training loop does: data arrives in random batch sizes, one
    /// step at a time is taken only while `steps_before_due() > 0`, due iterations run at once.
    /// Returns, per iteration, the env steps received when it ran.
    fn drive(limiter: &mut UtdLimiter, total: u64, seed: u64) -> Vec<u64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut at = Vec::new();
        let mut received = 0;
        while received < total {
            let batch = rng.random_range(1..=100u64).min(total - received);
            let mut left = batch;
            while left > 0 {
                while limiter.due() > 0 {
                    limiter.iteration_done();
                    at.push(limiter.env_steps());
                }
                let take = left.min(limiter.steps_before_due());
                limiter.receive(take);
                left -= take;
            }
            received += batch;
        }
        while limiter.due() > 0 {
            limiter.iteration_done();
            at.push(limiter.env_steps());
        }
        at
    }

    #[test]
    fn sync_matches_the_reference_schedule() {
        // K = 8, W = 20: the reference updates after the chunks ending at 32, 40, 48, ...
        // (pre-increment counts 24, 32, ... >= 20).
        let mut limiter = UtdLimiter::new(UtdMode::Sync, 8, 16, 20);
        assert_eq!(limiter.steps_before_due(), 32);
        let at = drive(&mut limiter, 100, 1);
        assert_eq!(at, vec![32, 40, 48, 56, 64, 72, 80, 88, 96]);
        assert_eq!(limiter.earned(), 9);
        assert_eq!(limiter.due(), 0);
    }

    #[test]
    fn sync_holds_the_ratio_within_five_percent_over_any_ten_iterations() {
        for (k, g, w, seed) in [
            (8, 16, 5000, 1),
            (32, 16, 100, 2),
            (8, 80, 64, 3),
            (3, 7, 0, 4),
        ] {
            let mut limiter = UtdLimiter::new(UtdMode::Sync, k, g, w);
            let at = drive(&mut limiter, 20_000, seed);
            assert!(at.len() > 20);
            let target = g as f64 / k as f64;
            for window in at.windows(11) {
                // 10 iterations between the first and the last boundary of the window.
                let ratio = (10 * g) as f64 / (window[10] - window[0]) as f64;
                assert!(
                    (ratio / target - 1.0).abs() <= 0.05,
                    "K {k} G {g}: ratio {ratio} vs target {target}"
                );
            }
            assert!((limiter.achieved_utd() / target - 1.0).abs() < 0.05);
        }
    }

    #[test]
    fn nothing_is_due_during_the_warmup_of_a_new_phase() {
        let mut limiter = UtdLimiter::new(UtdMode::Sync, 10, 4, 0);
        drive(&mut limiter, 50, 5);
        assert_eq!(limiter.iterations(), 5);
        // Stage 2 begins at 53 steps: 30 policy-only steps, then the schedule restarts.
        limiter.receive(3);
        limiter.start_phase(30);
        assert!(!limiter.updating());
        assert_eq!(limiter.steps_before_due(), 40);
        limiter.receive(39);
        assert_eq!(limiter.due(), 0);
        limiter.receive(1);
        assert_eq!(limiter.due(), 1);
        assert_eq!(limiter.steps_before_due(), 0);
    }

    #[test]
    fn async_updates_flat_out_after_the_warmup_and_reports_its_ratio() {
        let mut limiter = UtdLimiter::new(UtdMode::Async, 8, 16, 16);
        limiter.receive(23);
        assert_eq!(limiter.due(), 0);
        assert_eq!(limiter.steps_before_due(), u64::MAX);
        limiter.receive(1);
        assert_eq!(limiter.due(), 1);
        for _ in 0..5 {
            limiter.iteration_done();
        }
        assert_eq!(limiter.due(), 1);
        limiter.receive(12);
        // 5 iterations of 16 critic updates over the 20 steps past the warm-up chunks (16).
        assert_eq!(limiter.achieved_utd(), 4.0);
        assert_eq!(limiter.target_utd(), 2.0);
    }

    #[test]
    fn a_backlog_is_clamped_not_burst() {
        // An async checkpoint that fell behind, resumed in sync mode.
        let mut limiter = UtdLimiter::new(UtdMode::Async, 8, 16, 0);
        limiter.receive(800);
        limiter.iteration_done();
        limiter.reconfigure(UtdMode::Sync, 8, 16);
        assert_eq!(limiter.due(), 99);
        assert_eq!(limiter.clamp_backlog(), 98);
        assert_eq!(limiter.due(), 1);
        assert_eq!(limiter.forgiven(), 98);
        limiter.iteration_done();
        assert_eq!(limiter.due(), 0);
        assert_eq!(limiter.steps_before_due(), 8);
        // Nothing to clamp in steady state.
        assert_eq!(limiter.clamp_backlog(), 0);
    }

    #[test]
    fn the_limiter_round_trips_through_json() {
        let mut limiter = UtdLimiter::new(UtdMode::Sync, 8, 16, 20);
        drive(&mut limiter, 77, 9);
        let back: UtdLimiter =
            serde_json::from_str(&serde_json::to_string(&limiter).unwrap()).unwrap();
        assert_eq!(back, limiter);
    }
}
