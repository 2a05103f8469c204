//! The numerical consequences of spec 3.5 with n = 1000 levels.
use rfcl_core::config::{ForwardConfig, ScoreTransform};
use rfcl_curriculum::forward::Forward;
use rfcl_curriculum::rank::Transform;

/// P_S mass on the score-3, score-2 and score-1 groups for `counts` levels of each.
fn group_masses(counts: [usize; 3]) -> [f64; 3] {
    let scores: Vec<f64> = [3.0, 2.0, 1.0]
        .iter()
        .zip(counts)
        .flat_map(|(&score, count)| std::iter::repeat_n(score, count))
        .collect();
    let p_s = Transform {
        kind: ScoreTransform::Rankmin,
        temperature: 0.1,
        power_eps: 0.0,
    }
    .probabilities(&scores);
    let mut masses = [0.0; 3];
    for (score, p) in scores.iter().zip(p_s) {
        masses[3 - *score as usize] += p;
    }
    masses
}

/// `actual` matches a table entry written to the precision `precision`.
fn assert_entry(actual: f64, table: f64, precision: f64) {
    assert!(
        (actual - table).abs() <= precision / 2.0,
        "{actual:e} is not {table:e} (to {precision:e})"
    );
}

#[test]
fn spec_table_of_group_masses() {
    // (counts of score 3 / 2 / 1, masses from the table, precision of each entry)
    let rows: [([usize; 3], [f64; 3], [f64; 3]); 4] = [
        ([1, 999, 0], [1.0, 1e-24, 0.0], [1e-12, 1e-24, 0.0]),
        ([300, 200, 500], [0.996, 0.004, 1e-5], [1e-3, 1e-3, 1e-5]),
        ([0, 999, 1], [0.0, 0.999, 0.001], [0.0, 1e-3, 1e-3]),
        ([5, 5, 990], [0.998, 0.002, 1e-20], [1e-3, 1e-3, 1e-20]),
    ];
    for (counts, table, precision) in rows {
        let masses = group_masses(counts);
        assert!((masses.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        for g in 0..3 {
            assert_entry(masses[g], table[g], precision[g]);
        }
    }
}

#[test]
fn sampling_is_uniform_at_the_start_of_stage_2() {
    let config = ForwardConfig {
        include_demo_starts: false,
        ..ForwardConfig::default()
    };
    let forward = Forward::new(config, &[]).unwrap();
    for p in forward.probabilities() {
        assert!((p - 1e-3).abs() < 1e-15);
    }
}
