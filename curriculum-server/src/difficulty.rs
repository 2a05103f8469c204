//! Per-demo difficulty during stage 1 (docs/ALGORITHM.md section 2.10, rfcl's addition): how each
//! demo's frontier t_i moved over env steps, how often episodes start from it and succeed there, and
//! which demos have stalled while the others advance. The reverse curriculum itself does not read
//! any of it; it is what the dashboard, `/metrics`, summary.json and `rfcl demos select` show.
use serde::{Deserialize, Serialize};

use crate::reverse::{DemoProgress, ReportEffect};

/// Stage-1 history of one demo.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DemoRecord {
    /// Stage-1 episodes started from this demo (any start index).
    pub episodes: u64,
    /// Of which started at the demo's frontier t_i (the ones the curriculum counts, spec 2.6).
    pub frontier_episodes: u64,
    /// Of which ended in success.
    pub frontier_successes: u64,
    /// `(env steps, t_i)` after each move of the frontier, oldest first. t_i only decreases, so
    /// this holds at most S_i / δ + 1 points.
    pub frontier: Vec<(u64, u32)>,
    /// Env steps when the frontier last moved or the demo became solved (0 before any move).
    pub last_change_env_steps: u64,
    /// Env steps when the demo became solved.
    pub solved_env_steps: Option<u64>,
}

/// Stage-1 histories of all demos, updated by every stage-1 report.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Difficulty {
    demos: Vec<DemoRecord>,
}

/// What [`Difficulty::assess`] says of one demo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DemoAssessment {
    /// Demo states the frontier moved back per 10,000 env steps (until solved).
    pub speed: f64,
    /// Env steps since the frontier last moved (0 once solved).
    pub env_steps_since_move: u64,
    /// Share of all stage-1 episodes that started from this demo.
    pub episode_share: f64,
    /// Success rate of all episodes started at the frontier (not only the last m).
    pub frontier_success_rate: f64,
    /// Stalled: see [`is_stalled`].
    pub stalled: bool,
}

impl Difficulty {
    /// Records one applied stage-1 report: an episode started at `start_index` of `demo`, which
    /// the curriculum applied with `effect`, leaving the demos at `progress`; `env_steps` is the
    /// run's count including it.
    pub fn record(
        &mut self,
        demo: usize,
        success: bool,
        effect: &ReportEffect,
        progress: &[DemoProgress],
        env_steps: u64,
    ) {
        // Snapshots written before this history existed restore it empty.
        if self.demos.len() < progress.len() {
            self.demos.resize_with(progress.len(), DemoRecord::default);
        }
        let Some(d) = self.demos.get_mut(demo) else {
            return;
        };
        d.episodes += 1;
        if matches!(effect, ReportEffect::NotFrontier) {
            return;
        }
        d.frontier_episodes += 1;
        d.frontier_successes += success as u64;
        if let ReportEffect::Changed {
            advanced,
            newly_solved,
        } = effect
        {
            for &i in advanced {
                let r = &mut self.demos[i];
                r.frontier.push((env_steps, progress[i].start_step as u32));
                r.last_change_env_steps = env_steps;
            }
            for &i in newly_solved {
                let r = &mut self.demos[i];
                r.solved_env_steps = Some(env_steps);
                r.last_change_env_steps = env_steps;
            }
        }
    }

    pub fn demos(&self) -> &[DemoRecord] {
        &self.demos
    }

    /// Assesses every demo at `env_steps` (the run's count now, or when stage 1 ended). A demo
    /// stalls after `stall_after` env steps without a move while another demo moved.
    pub fn assess(
        &self,
        progress: &[DemoProgress],
        env_steps: u64,
        stall_after: u64,
    ) -> Vec<DemoAssessment> {
        let empty = DemoRecord::default();
        let record = |i: usize| self.demos.get(i).unwrap_or(&empty);
        let total_episodes: u64 = self.demos.iter().map(|d| d.episodes).sum();
        progress
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let r = record(i);
                let others_last_change = (0..progress.len())
                    .filter(|&j| j != i)
                    .map(|j| record(j).last_change_env_steps)
                    .max();
                let until = r.solved_env_steps.unwrap_or(env_steps);
                DemoAssessment {
                    speed: frontier_speed(p.num_states - 1 - p.start_step, until),
                    env_steps_since_move: match p.solved {
                        true => 0,
                        false => env_steps.saturating_sub(r.last_change_env_steps),
                    },
                    episode_share: r.episodes as f64 / total_episodes.max(1) as f64,
                    frontier_success_rate: r.frontier_successes as f64
                        / r.frontier_episodes.max(1) as f64,
                    stalled: is_stalled(
                        p.solved || p.start_step == 0,
                        r.last_change_env_steps,
                        others_last_change,
                        env_steps,
                        stall_after,
                    ),
                }
            })
            .collect()
    }
}

/// A demo's frontier speed (docs/ALGORITHM.md 2.10): `states_moved` states (S_i - 1 - t_i) over
/// `env_steps` env steps of stage 1, per 10,000 env steps; 0 before any env step.
pub fn frontier_speed(states_moved: usize, env_steps: u64) -> f64 {
    match env_steps {
        0 => 0.0,
        n => states_moved as f64 * 10_000.0 / n as f64,
    }
}

/// Whether a demo has stalled (docs/ALGORITHM.md 2.10): its frontier has not reached its first
/// state (`at_start_or_solved` is false), has not moved for at least `stall_after` env steps
/// (counted from `last_change`, 0 if it never moved), and some other demo's frontier moved or became
/// solved after this one's last move (`others_last_change`, the latest of theirs). A curriculum
/// where nothing moves at all (early training) flags no demo, and neither is a demo at t_i = 0: the
/// reverse curriculum hardly draws it while another demo has t_i > 0 (2.2), so its solve waits on
/// the others.
pub fn is_stalled(
    at_start_or_solved: bool,
    last_change: u64,
    others_last_change: Option<u64>,
    env_steps: u64,
    stall_after: u64,
) -> bool {
    !at_start_or_solved
        && env_steps.saturating_sub(last_change) >= stall_after
        && others_last_change.is_some_and(|o| o > last_change)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reverse::{DemoMeta, Reverse};
    use rfcl_core::config::ReverseConfig;

    #[test]
    fn speed_is_states_per_ten_thousand_env_steps() {
        // 24 states in 60,000 env steps: 4 per 10k.
        assert_eq!(frontier_speed(24, 60_000), 4.0);
        assert_eq!(frontier_speed(3, 0), 0.0);
    }

    #[test]
    fn a_demo_stalls_only_when_another_moved_after_it() {
        // Unmoved since 10k, another moved at 40k, now 60k, threshold 50k: stalled.
        assert!(is_stalled(false, 10_000, Some(40_000), 60_000, 50_000));
        // 49,999 env steps without a move: not yet.
        assert!(!is_stalled(false, 10_001, Some(40_000), 60_000, 50_000));
        // Nobody moved after it (early training, or it is the latest mover): not stalled.
        assert!(!is_stalled(false, 0, Some(0), 60_000, 50_000));
        assert!(!is_stalled(false, 0, None, 60_000, 50_000));
        // Solved demos, and demos at their first state, never stall.
        assert!(!is_stalled(true, 0, Some(40_000), 600_000, 50_000));
    }

    fn meta(actions: usize) -> DemoMeta {
        let mut success = vec![false; actions];
        success[actions - 1] = true;
        DemoMeta {
            success,
            reset_seed: None,
        }
    }

    #[test]
    fn reports_build_each_demos_history_and_assessment() {
        // Two demos of 9 states (8 actions, one trailing success state kept: S = 9), δ = 4, m = 1.
        let config = ReverseConfig {
            reverse_step_size: 4,
            per_demo_buffer_size: 1,
            ..ReverseConfig::default()
        };
        let mut reverse = Reverse::new(config, &[meta(8), meta(8)], 100).unwrap();
        assert_eq!(reverse.demos()[0].num_states, 9);
        let mut difficulty = Difficulty::default();
        let apply = |reverse: &mut Reverse,
                     difficulty: &mut Difficulty,
                     (demo, start, ok, steps): (usize, usize, bool, u64)| {
            let effect = reverse.report(demo, start, ok).unwrap();
            difficulty.record(demo, ok, &effect, reverse.demos(), steps);
        };
        // Demo 0: a failure at its frontier (8), an episode off the frontier, then a success that
        // moves t_0 from 8 to 4 at 10k env steps. Demo 1: one failure at its frontier.
        apply(&mut reverse, &mut difficulty, (0, 8, false, 1_000));
        apply(&mut reverse, &mut difficulty, (1, 8, false, 2_000));
        apply(&mut reverse, &mut difficulty, (0, 5, true, 3_000));
        apply(&mut reverse, &mut difficulty, (0, 8, true, 10_000));
        let r = &difficulty.demos()[0];
        assert_eq!(
            (r.episodes, r.frontier_episodes, r.frontier_successes),
            (3, 2, 1)
        );
        assert_eq!(r.frontier, vec![(10_000, 4)]);
        assert_eq!(r.last_change_env_steps, 10_000);

        let a = difficulty.assess(reverse.demos(), 60_000, 50_000);
        // Demo 0: 4 states in 60k env steps; 1 of 2 frontier episodes succeeded; 3 of 4 episodes.
        assert!((a[0].speed - 4.0 * 10_000.0 / 60_000.0).abs() < 1e-12);
        assert_eq!(a[0].env_steps_since_move, 50_000);
        assert_eq!(a[0].frontier_success_rate, 0.5);
        assert_eq!(a[0].episode_share, 0.75);
        // Demo 0 moved last, so it is not stalled although 50k passed; demo 1 never moved while
        // demo 0 did, 60k ago at the start: stalled.
        assert!(!a[0].stalled);
        assert!(a[1].stalled);
        assert_eq!(a[1].speed, 0.0);
        assert_eq!(a[1].frontier_success_rate, 0.0);
        // Demo 0 solves: 4 → 0 at 70k, then solved at 80k; its speed freezes at 8 states / 80k.
        apply(&mut reverse, &mut difficulty, (0, 4, true, 70_000));
        // At t_0 = 0 and unsolved for 130k env steps: not stalled, its solve waits on demo 1.
        let a = difficulty.assess(reverse.demos(), 200_000, 50_000);
        assert_eq!(reverse.demos()[0].start_step, 0);
        assert!(!a[0].stalled && a[1].stalled);
        apply(&mut reverse, &mut difficulty, (0, 0, true, 80_000));
        let a = difficulty.assess(reverse.demos(), 200_000, 50_000);
        assert_eq!(difficulty.demos()[0].solved_env_steps, Some(80_000));
        assert_eq!(a[0].speed, 1.0);
        assert_eq!(a[0].env_steps_since_move, 0);
        assert!(!a[0].stalled && a[1].stalled);
        assert_eq!(a[1].env_steps_since_move, 200_000);
    }
}
