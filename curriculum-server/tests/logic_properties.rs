//! Property tests of the curriculum logic.
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::{
    CurriculumMethod, ForwardConfig, LevelMix, ReverseConfig, RunConfig, ScoreTransform,
    StartStepSampler,
};
use rfcl_curriculum::forward::level_probabilities;
use rfcl_curriculum::rank::Transform;
use rfcl_curriculum::{Assignment, Curriculum, DemoMeta, EpisodeOutcome, ReportEffect, Reverse};

fn transform_kind() -> impl Strategy<Value = ScoreTransform> {
    use ScoreTransform::*;
    proptest::sample::select(vec![Rankmin, Rank, Constant, Identity, Power, Softmax])
}

fn sampler() -> impl Strategy<Value = StartStepSampler> {
    use StartStepSampler::*;
    proptest::sample::select(vec![
        Geometric,
        FixedPoint,
        Uniform,
        UniformSpike,
        UniformStep,
    ])
}

/// Any value, special ones included, and many ties.
fn value() -> impl Strategy<Value = f64> {
    prop_oneof![
        any::<f64>(),
        (0u8..4).prop_map(f64::from),
        Just(f64::INFINITY),
        Just(f64::NEG_INFINITY),
        Just(f64::NAN),
        Just(0.0),
    ]
}

fn assert_distribution(p: &[f64], len: usize) {
    assert_eq!(p.len(), len);
    assert!(p.iter().all(|&x| x.is_finite() && x >= 0.0), "{p:?}");
    assert!((p.iter().sum::<f64>() - 1.0).abs() < 1e-9, "{p:?}");
}

fn demos() -> impl Strategy<Value = Vec<DemoMeta>> {
    let demo = (
        prop::collection::vec(any::<bool>(), 0..30),
        any::<Option<u64>>(),
    )
        .prop_map(|(success, reset_seed)| DemoMeta {
            success,
            reset_seed,
        });
    prop::collection::vec(demo, 1..6)
}

/// A small run configuration that can reach stage 2 quickly.
fn run_config(seed: u64, m: u32, step: u32, method: CurriculumMethod) -> RunConfig {
    let mut config = RunConfig {
        seed,
        ..RunConfig::default()
    };
    config.reverse.per_demo_buffer_size = m;
    config.reverse.reverse_step_size = step;
    config.reverse.curriculum_method = method;
    config.forward.num_seeds = 20;
    config
}

/// Acquires `batch` resets, then reports them in order with outcomes drawn from `outcomes`.
fn run(
    curriculum: &mut Curriculum,
    outcomes: &mut ChaCha8Rng,
    rounds: usize,
    batch: usize,
) -> Vec<Assignment> {
    let mut seen = Vec::new();
    for round in 0..rounds {
        let Ok(leases) = (0..batch)
            .map(|_| curriculum.acquire())
            .collect::<Result<Vec<_>, _>>()
        else {
            break;
        };
        for lease in &leases {
            let outcome = EpisodeOutcome {
                success_at_end: outcomes.random_bool(0.8),
                episode_return: outcomes.random::<f64>() * 50.0 - 10.0,
            };
            curriculum.report(lease, outcome, round as u64).unwrap();
        }
        seen.extend(leases);
    }
    seen
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    #[test]
    fn transforms_give_distributions(
        x in prop::collection::vec(value(), 1..300),
        kind in transform_kind(),
        temperature in prop_oneof![0.001..10.0, Just(0.1)],
        power_eps in prop_oneof![Just(0.0), Just(1e-3)],
    ) {
        let p = Transform { kind, temperature, power_eps }.probabilities(&x);
        assert_distribution(&p, x.len());
    }

    #[test]
    fn level_mix_gives_distributions(
        levels in prop::collection::vec((value(), 0u64..5000), 1..1200),
        score_transform in transform_kind(),
        staleness_transform in transform_kind(),
        staleness_coef in 0.0..=1.0,
        paper in any::<bool>(),
    ) {
        let config = ForwardConfig {
            score_transform,
            staleness_transform,
            staleness_coef,
            mix: if paper { LevelMix::Paper } else { LevelMix::Reference },
            ..ForwardConfig::default()
        };
        let (scores, staleness): (Vec<f64>, Vec<f64>) =
            levels.iter().map(|&(s, c)| (s, c as f64)).unzip();
        assert_distribution(&level_probabilities(&config, &scores, &staleness), levels.len());
    }

    /// t_i never increases, moves back by exactly min(δ, t_i) on an advance, stays within the
    /// demo, and a demo is solved only at t_i = 0 after m more frontier successes there.
    #[test]
    fn reverse_curriculum_invariants(
        demos in demos(),
        m in 1u32..4,
        step in 1u32..6,
        global in any::<bool>(),
        sampler in sampler(),
        seed in any::<u64>(),
    ) {
        let method = if global { CurriculumMethod::Global } else { CurriculumMethod::PerDemo };
        let config = ReverseConfig {
            per_demo_buffer_size: m,
            reverse_step_size: step,
            curriculum_method: method,
            start_step_sampler: sampler,
            ..ReverseConfig::default()
        };
        let mut reverse = Reverse::new(config, &demos, 100).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        // Per demo, its frontier reports as (start index, success).
        let mut frontier: Vec<Vec<(usize, bool)>> = vec![Vec::new(); demos.len()];
        for _ in 0..2000 {
            let choice = reverse.sample(&mut rng);
            let before: Vec<usize> = reverse.demos().iter().map(|d| d.start_step).collect();
            let d = &reverse.demos()[choice.demo];
            prop_assert!(choice.start_index < d.num_states);
            prop_assert!(choice.time_limit >= 1 && choice.time_limit <= 100);
            let success = rng.random_bool(0.7);
            let effect = reverse.report(choice.demo, choice.start_index, success).unwrap();
            if choice.start_index == before[choice.demo] {
                frontier[choice.demo].push((choice.start_index, success));
            } else {
                prop_assert_eq!(&effect, &ReportEffect::NotFrontier);
            }
            let (advanced, newly_solved) = match effect {
                ReportEffect::Changed { advanced, newly_solved } => (advanced, newly_solved),
                _ => (vec![], vec![]),
            };
            for (i, d) in reverse.demos().iter().enumerate() {
                let expected = if advanced.contains(&i) {
                    before[i].saturating_sub(step as usize)
                } else {
                    before[i]
                };
                prop_assert_eq!(d.start_step, expected);
                prop_assert!(d.start_step < d.num_states);
            }
            for &i in &newly_solved {
                prop_assert_eq!(before[i], 0);
                if !global {
                    let last = &frontier[i][frontier[i].len().saturating_sub(m as usize)..];
                    prop_assert_eq!(last.len(), m as usize);
                    prop_assert!(last.iter().all(|&r| r == (0, true)));
                }
            }
        }
    }

    #[test]
    fn same_seed_same_sequence(
        demos in demos(),
        seed in any::<u64>(),
        m in 1u32..3,
        global in any::<bool>(),
    ) {
        let method = if global { CurriculumMethod::Global } else { CurriculumMethod::PerDemo };
        let config = run_config(seed, m, 8, method);
        let mut a = Curriculum::new(&config, &demos).unwrap();
        let mut b = Curriculum::new(&config, &demos).unwrap();
        let seq_a = run(&mut a, &mut ChaCha8Rng::seed_from_u64(seed ^ 1), 300, 4);
        let seq_b = run(&mut b, &mut ChaCha8Rng::seed_from_u64(seed ^ 1), 300, 4);
        prop_assert_eq!(seq_a, seq_b);
        prop_assert_eq!(a, b);
    }

    #[test]
    fn snapshot_restore_continues_identically(
        demos in demos(),
        seed in any::<u64>(),
        before in 0usize..300,
        batch in 1usize..8,
    ) {
        let config = run_config(seed, 1, 8, CurriculumMethod::PerDemo);
        let mut original = Curriculum::new(&config, &demos).unwrap();
        let mut outcomes = ChaCha8Rng::seed_from_u64(seed);
        run(&mut original, &mut outcomes, before, batch);

        let snapshot = serde_json::to_string(&original).unwrap();
        let mut restored: Curriculum = serde_json::from_str(&snapshot).unwrap();
        prop_assert_eq!(&restored, &original);

        let mut outcomes_restored = outcomes.clone();
        let seq_original = run(&mut original, &mut outcomes, 200, batch);
        let seq_restored = run(&mut restored, &mut outcomes_restored, 200, batch);
        prop_assert_eq!(seq_original, seq_restored);
        prop_assert_eq!(restored, original);
    }
}
