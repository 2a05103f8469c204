//! Stage 1: the per-demo reverse curriculum (spec 2).
//!
//! Each demo i keeps S_i reset states, a start step t_i that only moves back (towards state 0), a
//! FIFO of its last m frontier outcomes and a solved flag. A reset draws a demo with weight t_i/S_i,
//! then a start index at or after t_i, and gets a time limit that grows with the distance to the end
//! of the demo. Each report is applied at once (deviation 4).
use std::collections::VecDeque;

use rand::Rng;
use rfcl_core::config::{CurriculumMethod, ReverseConfig, StartStepSampler, TimeLimitFormula};
use serde::{Deserialize, Serialize};

use crate::rank::{draw, normalise};
use crate::CurriculumError;

/// What the curricula need to know about one demo.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DemoMeta {
    /// Per action, whether the state it led to is a success state. Its length is T_i, the demo's
    /// number of actions (spec 6.1: `success` has shape [T]).
    pub success: Vec<bool>,
    /// The seed the demo's episode was reset with (its `reset_kwargs`), if it has one.
    pub reset_seed: Option<u64>,
}

impl DemoMeta {
    /// T_i, the number of actions.
    pub fn num_actions(&self) -> usize {
        self.success.len()
    }
}

/// Stage-1 state of one demo (spec 2.1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DemoProgress {
    /// T_i: actions in the demo.
    pub num_actions: usize,
    /// S_i: reset states kept after light truncation; indices run 0..S_i-1.
    pub num_states: usize,
    /// t_i: the frontier start step; starts at S_i - 1 and only decreases.
    pub start_step: usize,
    /// The last m frontier outcomes (success at end), oldest first; pre-filled with failures.
    pub successes: VecDeque<bool>,
    pub solved: bool,
}

impl DemoProgress {
    fn new(meta: &DemoMeta, config: &ReverseConfig) -> Self {
        let num_success = meta.success.iter().filter(|&&s| s).count();
        let num_states = kept_states(
            meta.num_actions(),
            num_success,
            config.max_trailing_success_states as usize,
        );
        Self {
            num_actions: meta.num_actions(),
            num_states,
            start_step: num_states - 1,
            successes: failures(config.per_demo_buffer_size as usize),
            solved: false,
        }
    }

    /// Fraction of successes among the last m frontier episodes.
    pub fn frontier_success_rate(&self) -> f64 {
        success_rate(&self.successes)
    }

    /// t_i / (S_i - 1): how far back the frontier still is (1 = at the end, 0 = at the start).
    pub fn start_step_frac(&self) -> f64 {
        match self.num_states - 1 {
            0 => 0.0,
            last => self.start_step as f64 / last as f64,
        }
    }

    /// One advance (spec 2.6): t_i ← max(t_i - δ, 0), or, already at 0, solved.
    fn advance(&mut self, step_size: usize) -> Option<Change> {
        if self.start_step > 0 {
            self.start_step = self.start_step.saturating_sub(step_size);
            Some(Change::SteppedBack)
        } else if !self.solved {
            self.solved = true;
            Some(Change::Solved)
        } else {
            None
        }
    }
}

enum Change {
    SteppedBack,
    Solved,
}

/// A stage-1 reset: which demo, which of its states, and the episode's time limit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct StartChoice {
    pub demo: usize,
    pub start_index: usize,
    pub time_limit: u32,
}

/// What a report changed.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum ReportEffect {
    /// The episode did not start at its demo's current t_i, so it was not counted (spec 2.6).
    NotFrontier,
    /// Counted in the success FIFOs; no start step moved.
    Counted,
    /// The curriculum moved: these demos stepped back and these became solved.
    Changed {
        advanced: Vec<usize>,
        newly_solved: Vec<usize>,
    },
}

/// The reverse curriculum over all demos (spec 2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Reverse {
    config: ReverseConfig,
    /// H, the env's own horizon; it caps every time limit.
    horizon: u32,
    demos: Vec<DemoProgress>,
    /// The global history FIFO of length m·N, pre-filled with failures (spec 2.6, `global`).
    history: VecDeque<bool>,
}

impl Reverse {
    pub fn new(
        config: ReverseConfig,
        demos: &[DemoMeta],
        horizon: u32,
    ) -> Result<Self, CurriculumError> {
        // Configs built in code skip config resolution: hold them to the same rule it applies.
        config
            .validate()
            .map_err(|e| CurriculumError::InvalidConfig(e.to_string()))?;
        if demos.is_empty() {
            return Err(CurriculumError::NoDemos);
        }
        let m = config.per_demo_buffer_size as usize;
        Ok(Self {
            demos: demos
                .iter()
                .map(|d| DemoProgress::new(d, &config))
                .collect(),
            history: failures(m * demos.len()),
            config,
            horizon,
        })
    }

    pub fn config(&self) -> &ReverseConfig {
        &self.config
    }

    pub fn demos(&self) -> &[DemoProgress] {
        &self.demos
    }

    /// Probability of drawing each demo at a reset (spec 2.2).
    pub fn demo_probabilities(&self) -> Vec<f64> {
        let weights: Vec<f64> = self
            .demos
            .iter()
            .map(|d| demo_weight(d.start_step, d.num_states, self.config.solved_demo_weight))
            .collect();
        normalise(&weights)
    }

    /// Candidate start indices of `demo` with their probabilities (spec 2.3).
    pub fn start_distribution(&self, demo: usize) -> Result<Vec<(usize, f64)>, CurriculumError> {
        Ok(self.candidates(self.demo(demo)?))
    }

    /// Draws a reset (spec 2.4 steps 2 and 4, with the time limit of 2.5).
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> StartChoice {
        let demo = draw(&self.demo_probabilities(), rng);
        let d = &self.demos[demo];
        let candidates = self.candidates(d);
        let probs: Vec<f64> = candidates.iter().map(|&(_, p)| p).collect();
        let (start_index, _) = candidates[draw(&probs, rng)];
        StartChoice {
            demo,
            start_index,
            time_limit: time_limit(
                &self.config,
                d.num_actions,
                d.num_states,
                start_index,
                self.horizon,
            ),
        }
    }

    /// Applies one finished episode that started at `start_index` of `demo` (spec 2.6).
    pub fn report(
        &mut self,
        demo: usize,
        start_index: usize,
        success_at_end: bool,
    ) -> Result<ReportEffect, CurriculumError> {
        let step_size = self.config.reverse_step_size as usize;
        let d = self.demo(demo)?;
        if start_index != d.start_step {
            return Ok(ReportEffect::NotFrontier);
        }
        push(&mut self.demos[demo].successes, success_at_end);
        push(&mut self.history, success_at_end);

        let mut advanced = Vec::new();
        let mut newly_solved = Vec::new();
        let mut record = |index: usize, change: Option<Change>| match change {
            Some(Change::SteppedBack) => advanced.push(index),
            Some(Change::Solved) => newly_solved.push(index),
            None => {}
        };
        match self.config.curriculum_method {
            CurriculumMethod::PerDemo => {
                let d = &mut self.demos[demo];
                if d.successes.iter().all(|&s| s) {
                    d.successes = failures(d.successes.len());
                    record(demo, d.advance(step_size));
                }
            }
            CurriculumMethod::Global => {
                if success_rate(&self.history) >= self.config.global_success_threshold {
                    self.history = failures(self.history.len());
                    for (index, d) in self.demos.iter_mut().enumerate() {
                        record(index, d.advance(step_size));
                    }
                }
            }
        }
        Ok(if advanced.is_empty() && newly_solved.is_empty() {
            ReportEffect::Counted
        } else {
            ReportEffect::Changed {
                advanced,
                newly_solved,
            }
        })
    }

    /// Fraction of demos solved (spec 2.7).
    pub fn solved_frac(&self) -> f64 {
        let solved = self.demos.iter().filter(|d| d.solved).count();
        solved as f64 / self.demos.len() as f64
    }

    /// Whether stage 1 is over: solved fraction strictly greater than the threshold (spec 2.7).
    pub fn stage_1_done(&self) -> bool {
        self.solved_frac() > self.config.solved_frac_threshold
    }

    /// Mean of t_i / (S_i - 1) over the demos (`train_stats/start_step_frac_avg`, spec 2.7).
    pub fn start_step_frac_avg(&self) -> f64 {
        let total: f64 = self.demos.iter().map(DemoProgress::start_step_frac).sum();
        total / self.demos.len() as f64
    }

    fn candidates(&self, d: &DemoProgress) -> Vec<(usize, f64)> {
        start_distribution(
            self.config.start_step_sampler,
            &self.config.geometric_probs,
            d.start_step,
            d.num_states,
        )
    }

    fn demo(&self, demo: usize) -> Result<&DemoProgress, CurriculumError> {
        self.demos.get(demo).ok_or(CurriculumError::UnknownDemo {
            demo,
            count: self.demos.len(),
        })
    }
}

/// S_i, the reset states kept of a demo with T_i actions (spec 2.1): T_i + 1, minus the last
/// (n_succ - max_trailing) states when the demo has n_succ > max_trailing success-flagged steps.
pub fn kept_states(num_actions: usize, num_success: usize, max_trailing: usize) -> usize {
    num_actions + 1 - num_success.saturating_sub(max_trailing)
}

/// Unnormalised weight of a demo at a reset (spec 2.2): t_i / S_i, or `solved_weight` when t_i = 0.
pub fn demo_weight(start_step: usize, num_states: usize, solved_weight: f64) -> f64 {
    if start_step == 0 {
        solved_weight
    } else {
        start_step as f64 / num_states as f64
    }
}

/// Start indices a sampler can pick for a demo with frontier `t` and `num_states` states, with
/// their probabilities (spec 2.3). Indices are increasing and distinct; mass clipped onto the last
/// state is merged.
pub fn start_distribution(
    sampler: StartStepSampler,
    geometric_probs: &[f64],
    t: usize,
    num_states: usize,
) -> Vec<(usize, f64)> {
    let last = num_states - 1;
    let weighted: Vec<(usize, f64)> = match sampler {
        StartStepSampler::Geometric => {
            let mut merged: Vec<(usize, f64)> = Vec::new();
            for (offset, &p) in geometric_probs.iter().enumerate() {
                let index = (t + offset).min(last);
                match merged.last_mut() {
                    Some((i, mass)) if *i == index => *mass += p,
                    _ => merged.push((index, p)),
                }
            }
            merged
        }
        StartStepSampler::FixedPoint => vec![(t, 1.0)],
        StartStepSampler::Uniform => (0..num_states).map(|i| (i, 1.0)).collect(),
        StartStepSampler::UniformSpike => (0..num_states)
            .map(|i| (i, if i == t { 1.0 } else { 1.0 / last as f64 }))
            .collect(),
        StartStepSampler::UniformStep => (0..=t)
            .map(|i| (i, if i == t { 1.0 } else { 1.0 / t as f64 }))
            .collect(),
    };
    let weights: Vec<f64> = weighted.iter().map(|&(_, w)| w).collect();
    let probs = normalise(&weights);
    weighted.iter().map(|&(i, _)| i).zip(probs).collect()
}

/// The episode's time limit for a start at state `start` of a demo with T_i = `num_actions` and
/// S_i = `num_states` (spec 2.5), capped by the env horizon H:
/// * reference: offset + floor((S_i - s) / φ), with Python's float floor division;
/// * paper: 1 + (T_i - s) / φ, rounded down.
///
/// φ ≤ 0 disables the dynamic limit (the limit is H).
pub fn time_limit(
    config: &ReverseConfig,
    num_actions: usize,
    num_states: usize,
    start: usize,
    horizon: u32,
) -> u32 {
    let phi = config.demo_horizon_to_max_steps_ratio;
    if phi.is_nan() || phi <= 0.0 {
        return horizon;
    }
    let limit = match config.time_limit {
        TimeLimitFormula::Reference => {
            f64::from(config.time_limit_offset) + floor_div((num_states - start) as f64, phi)
        }
        TimeLimitFormula::Paper => (1.0 + num_actions.saturating_sub(start) as f64 / phi).floor(),
    };
    // `as` saturates: an enormous limit becomes u32::MAX and then H.
    (limit as u32).min(horizon)
}

/// Python's `a // b` for a ≥ 0 and b > 0: the floor of the exact quotient, which
/// `(a / b).floor()` misses when the rounded quotient lands on an integer (1 // 0.1 is 9).
fn floor_div(a: f64, b: f64) -> f64 {
    let quotient = (a - a % b) / b;
    let floor = quotient.floor();
    if quotient - floor > 0.5 {
        floor + 1.0
    } else {
        floor
    }
}

/// A FIFO of `len` failures.
fn failures(len: usize) -> VecDeque<bool> {
    VecDeque::from(vec![false; len])
}

/// Pushes onto a fixed-length FIFO, dropping its oldest entry.
fn push(fifo: &mut VecDeque<bool>, value: bool) {
    fifo.pop_front();
    fifo.push_back(value);
}

fn success_rate(fifo: &VecDeque<bool>) -> f64 {
    fifo.iter().filter(|&&s| s).count() as f64 / fifo.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// A demo of `num_actions` actions whose last `num_success` steps are successes.
    fn demo(num_actions: usize, num_success: usize) -> DemoMeta {
        let success = (0..num_actions)
            .map(|i| i >= num_actions - num_success)
            .collect();
        DemoMeta {
            success,
            reset_seed: Some(0),
        }
    }

    fn config(m: u32, step: u32) -> ReverseConfig {
        ReverseConfig {
            per_demo_buffer_size: m,
            reverse_step_size: step,
            ..ReverseConfig::default()
        }
    }

    #[test]
    fn kept_states_truncates_success_states_beyond_the_limit() {
        assert_eq!(kept_states(100, 30, 50), 101);
        assert_eq!(kept_states(100, 50, 50), 101);
        assert_eq!(kept_states(100, 60, 50), 91);
        assert_eq!(kept_states(0, 0, 50), 1);
        let reverse = Reverse::new(ReverseConfig::default(), &[demo(100, 60)], 100).unwrap();
        let d = &reverse.demos()[0];
        assert_eq!((d.num_actions, d.num_states, d.start_step), (100, 91, 90));
        assert_eq!(d.successes, VecDeque::from(vec![false; 3]));
    }

    #[test]
    fn demo_weights_use_states_and_the_solved_weight() {
        assert_eq!(demo_weight(5, 10, 1e-6), 0.5);
        assert_eq!(demo_weight(0, 10, 1e-6), 1e-6);
        let mut reverse = Reverse::new(config(1, 100), &[demo(9, 1), demo(9, 1)], 100).unwrap();
        assert_eq!(reverse.demo_probabilities(), vec![0.5, 0.5]);
        reverse.report(0, 9, true).unwrap();
        let p = reverse.demo_probabilities();
        // Weights 1e-6 and 0.9.
        assert!((p[0] - 1e-6 / 0.900001).abs() < 1e-15);
        assert!((p[1] - 0.9 / 0.900001).abs() < 1e-15);
    }

    #[test]
    fn geometric_offsets_clip_onto_the_last_state() {
        let probs = ReverseConfig::default().geometric_probs;
        let sampler = StartStepSampler::Geometric;
        assert_eq!(
            start_distribution(sampler, &probs, 10, 100),
            vec![
                (10, 0.5),
                (11, 0.25),
                (12, 0.125),
                (13, 0.0625),
                (14, 0.0625)
            ]
        );
        // t = S - 3: offsets 2, 3, 4 all land on the last state, 1/8 + 1/16 + 1/16.
        assert_eq!(
            start_distribution(sampler, &probs, 97, 100),
            vec![(97, 0.5), (98, 0.25), (99, 0.25)]
        );
        assert_eq!(
            start_distribution(sampler, &probs, 99, 100),
            vec![(99, 1.0)]
        );
    }

    #[test]
    fn other_samplers() {
        let probs = [1.0];
        assert_eq!(
            start_distribution(StartStepSampler::FixedPoint, &probs, 2, 5),
            vec![(2, 1.0)]
        );
        assert_eq!(
            start_distribution(StartStepSampler::Uniform, &probs, 2, 4),
            vec![(0, 0.25), (1, 0.25), (2, 0.25), (3, 0.25)]
        );
        // Spike: t = 1 weight 1, the other 3 indices 1/3 each: total 2.
        let spike = start_distribution(StartStepSampler::UniformSpike, &probs, 1, 4);
        let expected = [1.0 / 6.0, 0.5, 1.0 / 6.0, 1.0 / 6.0];
        for (i, ((index, p), e)) in spike.into_iter().zip(expected).enumerate() {
            assert_eq!(index, i);
            assert!((p - e).abs() < 1e-15, "P({i}) = {p}, not {e}");
        }
        // Step: t = 2 weight 1, indices 0 and 1 weight 1/2 each: total 2.
        assert_eq!(
            start_distribution(StartStepSampler::UniformStep, &probs, 2, 9),
            vec![(0, 0.25), (1, 0.25), (2, 0.5)]
        );
        for sampler in [
            StartStepSampler::UniformSpike,
            StartStepSampler::UniformStep,
        ] {
            assert_eq!(start_distribution(sampler, &probs, 0, 1), vec![(0, 1.0)]);
        }
    }

    #[test]
    fn reference_time_limit() {
        let c = ReverseConfig::default();
        // At the start, s = S - 1, φ = 3: 16 + floor(1/3) = 16.
        assert_eq!(time_limit(&c, 100, 101, 100, 100), 16);
        assert_eq!(time_limit(&c, 100, 101, 50, 100), 16 + 17);
        // Capped by the horizon.
        assert_eq!(time_limit(&c, 100, 101, 0, 40), 40);
        let plug = ReverseConfig {
            demo_horizon_to_max_steps_ratio: 1.25,
            ..c.clone()
        };
        assert_eq!(time_limit(&plug, 100, 101, 91, 100), 16 + 8);
        let tenth = ReverseConfig {
            demo_horizon_to_max_steps_ratio: 0.1,
            ..c.clone()
        };
        // Python: 1 // 0.1 == 9.0, where 1 / 0.1 == 10.0.
        assert_eq!(time_limit(&tenth, 100, 101, 100, 100), 16 + 9);
        let disabled = ReverseConfig {
            demo_horizon_to_max_steps_ratio: 0.0,
            ..c
        };
        assert_eq!(time_limit(&disabled, 100, 101, 100, 77), 77);
    }

    #[test]
    fn paper_time_limit() {
        let c = ReverseConfig {
            time_limit: TimeLimitFormula::Paper,
            ..ReverseConfig::default()
        };
        // 1 + (100 - 90) / 3 = 4.33 → 4.
        assert_eq!(time_limit(&c, 100, 101, 90, 100), 4);
        assert_eq!(time_limit(&c, 100, 101, 100, 100), 1);
        assert_eq!(time_limit(&c, 100, 101, 0, 20), 20);
    }

    #[test]
    fn per_demo_update_counts_frontier_successes_only() {
        let mut reverse = Reverse::new(config(3, 4), &[demo(9, 1)], 100).unwrap();
        // S = 10, t = 9.
        assert_eq!(reverse.report(0, 8, true), Ok(ReportEffect::NotFrontier));
        assert_eq!(reverse.report(0, 9, true), Ok(ReportEffect::Counted));
        // A failure occupies a slot but does not reset the FIFO.
        assert_eq!(reverse.report(0, 9, false), Ok(ReportEffect::Counted));
        // FIFO [false, true, false].
        assert_eq!(reverse.demos()[0].frontier_success_rate(), 1.0 / 3.0);
        assert_eq!(reverse.report(0, 9, true), Ok(ReportEffect::Counted));
        assert_eq!(reverse.report(0, 9, true), Ok(ReportEffect::Counted));
        let advanced = ReportEffect::Changed {
            advanced: vec![0],
            newly_solved: vec![],
        };
        assert_eq!(reverse.report(0, 9, true), Ok(advanced.clone()));
        let d = &reverse.demos()[0];
        assert_eq!(d.start_step, 5);
        assert_eq!(d.successes, VecDeque::from(vec![false; 3]));
        for _ in 0..3 {
            reverse.report(0, 5, true).unwrap();
        }
        // 5 - 4 = 1, then max(1 - 4, 0) = 0.
        assert_eq!(reverse.demos()[0].start_step, 1);
        for _ in 0..3 {
            reverse.report(0, 1, true).unwrap();
        }
        assert_eq!(reverse.demos()[0].start_step, 0);
        assert!(!reverse.demos()[0].solved);
        assert_eq!(reverse.report(0, 0, true), Ok(ReportEffect::Counted));
        assert_eq!(reverse.report(0, 0, true), Ok(ReportEffect::Counted));
        let solved = ReportEffect::Changed {
            advanced: vec![],
            newly_solved: vec![0],
        };
        assert_eq!(reverse.report(0, 0, true), Ok(solved));
        assert!(reverse.demos()[0].solved);
        for _ in 0..2 {
            reverse.report(0, 0, true).unwrap();
        }
        assert_eq!(reverse.report(0, 0, true), Ok(ReportEffect::Counted));
    }

    #[test]
    fn global_update_moves_every_demo() {
        let c = ReverseConfig {
            curriculum_method: CurriculumMethod::Global,
            ..config(2, 4)
        };
        // History of m·N = 4 entries; mean ≥ 0.9 needs all 4.
        let mut reverse = Reverse::new(c, &[demo(9, 1), demo(2, 1)], 100).unwrap();
        for _ in 0..3 {
            assert_eq!(reverse.report(0, 9, true), Ok(ReportEffect::Counted));
        }
        assert_eq!(
            reverse.report(1, 2, true),
            Ok(ReportEffect::Changed {
                advanced: vec![0, 1],
                newly_solved: vec![]
            })
        );
        let steps: Vec<usize> = reverse.demos().iter().map(|d| d.start_step).collect();
        assert_eq!(steps, vec![5, 0]);
        for _ in 0..4 {
            reverse.report(0, 5, true).unwrap();
        }
        // Demo 1 was already at 0: now solved; demo 0 stepped back.
        assert_eq!(reverse.demos()[0].start_step, 1);
        assert!(reverse.demos()[1].solved && !reverse.demos()[0].solved);
    }

    #[test]
    fn stage_1_ends_strictly_above_the_threshold() {
        let demos: Vec<DemoMeta> = (0..5).map(|_| demo(0, 0)).collect();
        let mut reverse = Reverse::new(config(1, 1), &demos, 100).unwrap();
        for i in 0..4 {
            reverse.report(i, 0, true).unwrap();
        }
        assert_eq!(reverse.solved_frac(), 0.8);
        assert!(!reverse.stage_1_done());
        reverse.report(4, 0, true).unwrap();
        assert!(reverse.stage_1_done());
    }

    #[test]
    fn sample_respects_the_frontier_and_time_limit() {
        let reverse = Reverse::new(ReverseConfig::default(), &[demo(20, 2)], 100).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for _ in 0..50 {
            // t = S - 1 = 20: every draw is the last state, limit 16 + floor(1/3).
            assert_eq!(
                reverse.sample(&mut rng),
                StartChoice {
                    demo: 0,
                    start_index: 20,
                    time_limit: 16
                }
            );
        }
        assert_eq!(reverse.start_step_frac_avg(), 1.0);
    }

    #[test]
    fn rejects_bad_input() {
        assert_eq!(
            Reverse::new(ReverseConfig::default(), &[], 100),
            Err(CurriculumError::NoDemos)
        );
        assert!(matches!(
            Reverse::new(config(0, 1), &[demo(3, 1)], 100),
            Err(CurriculumError::InvalidConfig(_))
        ));
        let mut reverse = Reverse::new(config(1, 1), &[demo(3, 1)], 100).unwrap();
        assert_eq!(
            reverse.report(1, 0, true),
            Err(CurriculumError::UnknownDemo { demo: 1, count: 1 })
        );
    }

    #[test]
    fn geometric_probs_must_sum_to_one_as_config_resolution_requires() {
        let short = ReverseConfig {
            geometric_probs: vec![0.5, 0.25, 0.15],
            ..ReverseConfig::default()
        };
        let Err(CurriculumError::InvalidConfig(why)) = Reverse::new(short, &[demo(3, 1)], 100)
        else {
            panic!("probabilities summing to 0.9 were accepted");
        };
        assert!(
            why.contains("reverse.geometric_probs") && why.contains("must sum to 1"),
            "{why}"
        );
        // The same rule, word for word, as a resolved config gets.
        let mut run = rfcl_core::config::RunConfig::default();
        run.reverse.geometric_probs = vec![0.5, 0.25, 0.15];
        assert!(
            why.ends_with(&run.validate().unwrap_err().to_string()),
            "{why}"
        );
    }
}
