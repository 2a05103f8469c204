//! Stage 2: the seed-based forward curriculum, a simplified PLR (spec 3).
//!
//! Levels are env seeds 0..n-1 and, with `include_demo_starts` (deviation 3), one level per demo
//! initial state. Each level keeps its last episode returns, a score derived from them and a
//! staleness count. A level is drawn on every acquire and scored when its episode is reported
//! (deviation 4).
use std::collections::VecDeque;

use rand::Rng;
use rfcl_core::config::{ForwardConfig, ForwardScore, LevelMix};
use serde::{Deserialize, Serialize};

use crate::rank::{draw_with, normalise, Transform, POWER_EPS_WITHOUT_STALENESS};
use crate::reverse::DemoMeta;
use crate::CurriculumError;

/// Score of a level that has not been solved in its last k episodes (spec 3.3).
pub const SCORE_UNSOLVED: f64 = 2.0;
/// Score of a level solved sometimes, but less than ω of the time: the highest priority (spec 3.3).
pub const SCORE_LEARNING: f64 = 3.0;
/// Score of a level solved at least ω of the time (spec 3.3).
pub const SCORE_EASY: f64 = 1.0;

/// How an env resets to a level.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum LevelSource {
    /// `env.reset(seed)` (spec 3.1).
    Seed(u64),
    /// The initial state of a demo: reset with the demo's own reset arguments (deviation 3).
    DemoStart {
        demo: usize,
        reset_seed: Option<u64>,
    },
}

/// Stage-2 state of one level (spec 3.2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Level {
    pub source: LevelSource,
    /// The last `returns_buffer_size` episode returns, oldest first; pre-filled with zeros.
    pub returns: VecDeque<f64>,
    pub score: f64,
    /// Draws since this level was last drawn.
    pub staleness: u64,
}

/// The forward curriculum over all levels (spec 3).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Forward {
    config: ForwardConfig,
    levels: Vec<Level>,
    /// P_S as a cumulative distribution, valid until a score changes (derived, never saved).
    #[serde(skip)]
    score_cdf: ScoreCdf,
}

/// A cache that takes no part in equality: two curricula with the same levels are equal whether
/// or not one of them has computed its cache.
#[derive(Debug, Clone, Default)]
struct ScoreCdf(Option<Vec<f64>>);

impl PartialEq for ScoreCdf {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl Forward {
    /// Levels 0..num_seeds-1 are the seeds; with `include_demo_starts`, level num_seeds + i is the
    /// initial state of demo i.
    pub fn new(config: ForwardConfig, demos: &[DemoMeta]) -> Result<Self, CurriculumError> {
        let seeds = (0..u64::from(config.num_seeds)).map(LevelSource::Seed);
        let demo_starts = demos
            .iter()
            .enumerate()
            .filter(|_| config.include_demo_starts)
            .map(|(demo, meta)| LevelSource::DemoStart {
                demo,
                reset_seed: meta.reset_seed,
            });
        let levels: Vec<Level> = seeds
            .chain(demo_starts)
            .map(|source| Level {
                source,
                returns: VecDeque::from(vec![0.0; config.returns_buffer_size as usize]),
                score: config.initial_score,
                staleness: 0,
            })
            .collect();
        if levels.is_empty() {
            return Err(CurriculumError::NoLevels);
        }
        // Configs built in code skip config resolution: hold them to the same rule it applies
        // (after the level count, which names the more specific problem).
        config
            .validate()
            .map_err(|e| CurriculumError::InvalidConfig(e.to_string()))?;
        Ok(Self {
            config,
            levels,
            score_cdf: ScoreCdf::default(),
        })
    }

    pub fn config(&self) -> &ForwardConfig {
        &self.config
    }

    pub fn levels(&self) -> &[Level] {
        &self.levels
    }

    /// The probability of drawing each level now (spec 3.5).
    pub fn probabilities(&self) -> Vec<f64> {
        let scores: Vec<f64> = self.levels.iter().map(|l| l.score).collect();
        let staleness: Vec<f64> = self.levels.iter().map(|l| l.staleness as f64).collect();
        level_probabilities(&self.config, &scores, &staleness)
    }

    /// Draws a level and updates staleness: every level +1, the drawn one 0 (spec 3.5).
    ///
    /// P is the mixture (1 - c)·P_S + c·P_C (the paper's mix: ½·P_S + ½·P_C), so one uniform number
    /// picks the component and then the level within it: the same distribution as drawing from
    /// [`probabilities`](Self::probabilities), but P_S (which changes only when a score does) is
    /// cached and P_C is computed only for the draws that need it.
    pub fn sample<R: Rng + ?Sized>(&mut self, rng: &mut R) -> usize {
        let (w_scores, _) = self.mixture_weights();
        let u: f64 = rng.random();
        let level = if u < w_scores {
            let cdf = self.score_cdf();
            match cdf.partition_point(|&c| c <= u / w_scores) {
                i if i < cdf.len() => i,
                // Rounding left the total just below u: take the last level that has mass.
                _ => (0..cdf.len())
                    .rev()
                    .find(|&i| i == 0 || cdf[i] > cdf[i - 1])
                    .unwrap_or(0),
            }
        } else {
            draw_with(
                &self.staleness_probabilities(),
                (u - w_scores) / (1.0 - w_scores),
            )
        };
        for l in &mut self.levels {
            l.staleness += 1;
        }
        self.levels[level].staleness = 0;
        level
    }

    /// The weights of P_S and P_C in the mixture (spec 3.5).
    fn mixture_weights(&self) -> (f64, f64) {
        match self.config.mix {
            LevelMix::Reference => (1.0 - self.config.staleness_coef, self.config.staleness_coef),
            LevelMix::Paper => (0.5, 0.5),
        }
    }

    fn transform(&self, kind: rfcl_core::config::ScoreTransform, temperature: f64) -> Transform {
        let power_eps = if self.config.staleness_coef > 0.0 {
            0.0
        } else {
            POWER_EPS_WITHOUT_STALENESS
        };
        Transform {
            kind,
            temperature,
            power_eps,
        }
    }

    /// P_S (spec 3.5 step 1).
    fn score_probabilities(&self) -> Vec<f64> {
        let scores: Vec<f64> = self.levels.iter().map(|l| l.score).collect();
        self.transform(self.config.score_transform, self.config.score_temperature)
            .probabilities(&scores)
    }

    /// P_C (spec 3.5 step 2; the paper's linear form for the paper mix).
    fn staleness_probabilities(&self) -> Vec<f64> {
        let staleness: Vec<f64> = self.levels.iter().map(|l| l.staleness as f64).collect();
        match self.config.mix {
            LevelMix::Reference => self
                .transform(
                    self.config.staleness_transform,
                    self.config.staleness_temperature,
                )
                .probabilities(&staleness),
            LevelMix::Paper => normalise(&staleness),
        }
    }

    fn score_cdf(&mut self) -> &[f64] {
        if self.score_cdf.0.is_none() {
            let mut total = 0.0;
            let cdf = self
                .score_probabilities()
                .into_iter()
                .map(|p| {
                    total += p;
                    total
                })
                .collect();
            self.score_cdf.0 = Some(cdf);
        }
        self.score_cdf.0.as_deref().expect("just computed")
    }

    /// The distribution [`sample`](Self::sample) draws from, computed its way (for tests: it must
    /// equal [`probabilities`](Self::probabilities)).
    pub fn sampling_distribution(&self) -> Vec<f64> {
        let (w_s, w_c) = self.mixture_weights();
        let p_s = self.score_probabilities();
        let p_c = self.staleness_probabilities();
        p_s.iter()
            .zip(&p_c)
            .map(|(s, c)| w_s * s + w_c * c)
            .collect()
    }

    /// Records a finished episode's return on its level and rescores it (spec 3.6); returns the
    /// new score.
    pub fn report(&mut self, level: usize, episode_return: f64) -> Result<f64, CurriculumError> {
        let count = self.levels.len();
        let l = self
            .levels
            .get_mut(level)
            .ok_or(CurriculumError::UnknownLevel { level, count })?;
        l.returns.pop_front();
        l.returns.push_back(episode_return);
        let score = match self.config.forward_curriculum {
            ForwardScore::SuccessOnceScore => success_once_score(
                &l.returns,
                self.config.score_window as usize,
                self.config.score_threshold,
            ),
        };
        if score != l.score {
            l.score = score;
            self.score_cdf.0 = None;
        }
        Ok(score)
    }
}

/// `success_once_score` (spec 3.3): with q the fraction of the last k returns that are > 0
/// (padding zeros count), 2 if q = 0, 3 if 0 < q < ω, 1 if q ≥ ω.
pub fn success_once_score(returns: &VecDeque<f64>, window: usize, threshold: f64) -> f64 {
    let successes = returns
        .iter()
        .rev()
        .take(window)
        .filter(|&&r| r > 0.0)
        .count();
    let q = successes as f64 / window as f64;
    if successes == 0 {
        SCORE_UNSOLVED
    } else if q < threshold {
        SCORE_LEARNING
    } else {
        SCORE_EASY
    }
}

/// The level sampling distribution (spec 3.5):
/// * reference: (1 - c)·P_S + c·P_C, P_S and P_C the configured transforms of the scores and of
///   the staleness counts;
/// * paper: P_S + P_C with the linear P_C = C_j / Σ C (uniform while every C_j is 0),
///   renormalised; the staleness transform and coefficient are unused.
pub fn level_probabilities(config: &ForwardConfig, scores: &[f64], staleness: &[f64]) -> Vec<f64> {
    let c = config.staleness_coef;
    let power_eps = if c > 0.0 {
        0.0
    } else {
        POWER_EPS_WITHOUT_STALENESS
    };
    let transform = |kind, temperature| Transform {
        kind,
        temperature,
        power_eps,
    };
    let p_s = transform(config.score_transform, config.score_temperature).probabilities(scores);
    let mixed: Vec<f64> = match config.mix {
        LevelMix::Reference => {
            let p_c = transform(config.staleness_transform, config.staleness_temperature)
                .probabilities(staleness);
            p_s.iter()
                .zip(&p_c)
                .map(|(s, st)| (1.0 - c) * s + c * st)
                .collect()
        }
        LevelMix::Paper => {
            let p_c = normalise(staleness);
            p_s.iter().zip(&p_c).map(|(s, st)| s + st).collect()
        }
    };
    normalise(&mixed)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn the_cached_mixture_sampler_draws_from_the_spec_distribution() {
        for mix in [LevelMix::Reference, LevelMix::Paper] {
            let config = ForwardConfig {
                num_seeds: 200,
                include_demo_starts: false,
                mix,
                ..ForwardConfig::default()
            };
            let mut forward = Forward::new(config, &[]).unwrap();
            let mut rng = ChaCha8Rng::seed_from_u64(3);
            for step in 0..3000 {
                let level = forward.sample(&mut rng);
                let ret = if rng.random_bool(0.4) { 1.0 } else { 0.0 };
                forward.report(level, ret).unwrap();
                if step % 97 == 0 {
                    let (a, b) = (forward.sampling_distribution(), forward.probabilities());
                    let worst = a
                        .iter()
                        .zip(&b)
                        .map(|(x, y)| (x - y).abs())
                        .fold(0.0, f64::max);
                    assert!(worst < 1e-12, "{mix:?} step {step}: {worst}");
                }
            }
            // Frequencies follow the distribution: the first draws of a fresh curriculum are uniform.
            let fresh = Forward::new(
                ForwardConfig {
                    num_seeds: 4,
                    include_demo_starts: false,
                    mix,
                    ..ForwardConfig::default()
                },
                &[],
            )
            .unwrap();
            let mut counts = [0u32; 4];
            for _ in 0..4000 {
                counts[fresh.clone().sample(&mut rng)] += 1;
            }
            assert!(
                counts.iter().all(|&c| (900..1100).contains(&c)),
                "{counts:?}"
            );
        }
    }

    fn seeds_only(num_seeds: u32) -> ForwardConfig {
        ForwardConfig {
            num_seeds,
            include_demo_starts: false,
            ..ForwardConfig::default()
        }
    }

    #[test]
    fn success_once_score_table() {
        let returns = |recent: &[f64]| {
            let mut r = VecDeque::from(vec![0.0; 20]);
            for &x in recent {
                r.pop_front();
                r.push_back(x);
            }
            r
        };
        assert_eq!(success_once_score(&returns(&[]), 5, 0.75), 2.0);
        assert_eq!(success_once_score(&returns(&[3.0]), 5, 0.75), 3.0);
        // q = 0.6
        assert_eq!(
            success_once_score(&returns(&[1.0, 0.0, 1.0, 1.0]), 5, 0.75),
            3.0
        );
        // q = 0.8
        assert_eq!(
            success_once_score(&returns(&[1.0, 1.0, 1.0, 1.0]), 5, 0.75),
            1.0
        );
        // Only the last 5 count: four old successes then five failures.
        assert_eq!(success_once_score(&returns(&[1.0; 4]), 5, 0.75), 1.0);
        let old = returns(&[1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!(success_once_score(&old, 5, 0.75), 2.0);
    }

    #[test]
    fn levels_are_seeds_then_demo_starts() {
        let demos = [
            DemoMeta {
                success: vec![true],
                reset_seed: Some(42),
            },
            DemoMeta {
                success: vec![true],
                reset_seed: None,
            },
        ];
        let forward = Forward::new(
            ForwardConfig {
                num_seeds: 2,
                ..ForwardConfig::default()
            },
            &demos,
        )
        .unwrap();
        let sources: Vec<LevelSource> = forward.levels().iter().map(|l| l.source).collect();
        assert_eq!(
            sources,
            vec![
                LevelSource::Seed(0),
                LevelSource::Seed(1),
                LevelSource::DemoStart {
                    demo: 0,
                    reset_seed: Some(42)
                },
                LevelSource::DemoStart {
                    demo: 1,
                    reset_seed: None
                },
            ]
        );
        let l = &forward.levels()[3];
        assert_eq!((l.score, l.staleness, l.returns.len()), (2.0, 0, 20));
        assert_eq!(forward.probabilities(), vec![0.25; 4]);
    }

    #[test]
    fn staleness_counts_draws() {
        let mut forward = Forward::new(seeds_only(3), &[]).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let first = forward.sample(&mut rng);
        let second = forward.sample(&mut rng);
        let staleness: Vec<u64> = forward.levels().iter().map(|l| l.staleness).collect();
        assert_eq!(staleness[second], 0);
        if first != second {
            assert_eq!(staleness[first], 1);
        }
        for (level, &s) in staleness.iter().enumerate() {
            if level != first && level != second {
                assert_eq!(s, 2);
            }
        }
    }

    #[test]
    fn reference_mix_is_0_9_scores_plus_0_1_staleness() {
        let config = ForwardConfig::default();
        // Equal scores: P_S uniform. Staleness [2, 1, 0]: ranks 2, 3, 4.
        let w = [2f64.powi(-10), 3f64.powi(-10), 4f64.powi(-10)];
        let total: f64 = w.iter().sum();
        let p = level_probabilities(&config, &[2.0; 3], &[2.0, 1.0, 0.0]);
        for (p, w) in p.iter().zip(w) {
            assert!((p - (0.9 / 3.0 + 0.1 * w / total)).abs() < 1e-12);
        }
        // With distinct staleness the single stalest level takes ~98% of P_C.
        let staleness: Vec<f64> = (0..1000).map(f64::from).collect();
        let p = level_probabilities(&config, &[2.0; 1000], &staleness);
        assert!((p[999] - 0.9 / 1000.0 - 0.1 * 0.982).abs() < 1e-3);
    }

    #[test]
    fn paper_mix_uses_linear_staleness() {
        let config = ForwardConfig {
            mix: LevelMix::Paper,
            ..ForwardConfig::default()
        };
        // P_S uniform [1/2, 1/2]; P_C = [3/4, 1/4]; sum / 2.
        let p = level_probabilities(&config, &[2.0, 2.0], &[3.0, 1.0]);
        assert!((p[0] - 0.625).abs() < 1e-15 && (p[1] - 0.375).abs() < 1e-15);
        assert_eq!(
            level_probabilities(&config, &[2.0, 2.0], &[0.0, 0.0]),
            vec![0.5, 0.5]
        );
    }

    #[test]
    fn report_rescores_only_that_level() {
        let mut forward = Forward::new(seeds_only(3), &[]).unwrap();
        assert_eq!(forward.report(1, 5.0), Ok(3.0));
        assert_eq!(forward.levels()[1].returns.back(), Some(&5.0));
        assert_eq!(forward.levels()[0].score, 2.0);
        let p = forward.probabilities();
        assert!(
            p[1] > 0.89,
            "a score-3 level takes nearly all of P_S: {p:?}"
        );
        assert_eq!(
            forward.report(3, 1.0),
            Err(CurriculumError::UnknownLevel { level: 3, count: 3 })
        );
    }

    #[test]
    fn rejects_bad_configs() {
        assert_eq!(
            Forward::new(seeds_only(0), &[]),
            Err(CurriculumError::NoLevels)
        );
        let wide = ForwardConfig {
            score_window: 21,
            ..seeds_only(1)
        };
        assert!(matches!(
            Forward::new(wide, &[]),
            Err(CurriculumError::InvalidConfig(_))
        ));
    }

    #[test]
    fn configs_built_in_code_meet_the_rule_of_resolved_ones() {
        // The score threshold is a success rate: the curriculum used to take any value here.
        let above_one = ForwardConfig {
            score_threshold: 1.5,
            ..seeds_only(3)
        };
        let Err(CurriculumError::InvalidConfig(why)) = Forward::new(above_one, &[]) else {
            panic!("a score threshold of 1.5 was accepted");
        };
        assert!(
            why.contains("forward.score_threshold") && why.contains("in [0, 1]"),
            "{why}"
        );
    }
}
