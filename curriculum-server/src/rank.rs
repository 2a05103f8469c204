//! Rank transforms (spec 3.4) and the probability vectors built from them.
//!
//! Every function here returns probabilities that are finite, non-negative and sum to 1 for any
//! input: weights are computed in log space and shifted by their maximum before exponentiation, so
//! `rank^-10` over thousands of levels cannot underflow to an all-zero vector. NaN inputs count as the
//! lowest possible value; when no entry has positive weight the result is uniform.
use rand::Rng;
use rfcl_core::config::ScoreTransform;
use serde::{Deserialize, Serialize};

/// The reference's ε in the `power` transform when the staleness coefficient is 0 (spec 3.4).
pub const POWER_EPS_WITHOUT_STALENESS: f64 = 1e-3;

/// A rank transform with its temperature β (spec 3.4).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    pub kind: ScoreTransform,
    /// β; the weight exponent is 1/β.
    pub temperature: f64,
    /// ε added to the values by the `power` transform.
    pub power_eps: f64,
}

impl Transform {
    /// Normalised probabilities of the values `x` under this transform (spec 3.4):
    /// * `rankmin`: rank_j = 1 + #{l : x_l ≥ x_j}, weight rank_j^(-1/β);
    /// * `rank`: ordinal rank (1 = highest), weight rank_j^(-1/β);
    /// * `constant`: uniform; `identity`: x_j (negative values count as 0);
    /// * `power`: (x_j + ε)^(1/β); `softmax`: exp(x_j / β).
    pub fn probabilities(&self, x: &[f64]) -> Vec<f64> {
        let x: Vec<f64> = x
            .iter()
            .map(|&v| if v.is_nan() { f64::NEG_INFINITY } else { v })
            .collect();
        let inv_beta = 1.0 / self.temperature;
        let log_rank = |rank: usize| -inv_beta * (rank as f64).ln();
        let log_weights: Vec<f64> = match self.kind {
            ScoreTransform::Rankmin => rankmin(&x).into_iter().map(log_rank).collect(),
            ScoreTransform::Rank => ordinal_rank(&x).into_iter().map(log_rank).collect(),
            ScoreTransform::Constant => vec![0.0; x.len()],
            ScoreTransform::Identity => x.iter().map(|&v| log_positive(v)).collect(),
            ScoreTransform::Power => x
                .iter()
                .map(|&v| inv_beta * log_positive(v + self.power_eps))
                .collect(),
            ScoreTransform::Softmax => x.iter().map(|&v| v * inv_beta).collect(),
        };
        normalise_log(&log_weights)
    }
}

/// `rankmin` ranks (spec 3.4): rank_j = 1 + #{l : x_l ≥ x_j}, so ties share the worst rank of
/// their group, plus one. `x` must hold no NaN.
pub fn rankmin(x: &[f64]) -> Vec<usize> {
    let mut sorted = x.to_vec();
    sorted.sort_by(f64::total_cmp);
    x.iter()
        .map(|&v| 1 + x.len() - sorted.partition_point(|&s| s < v))
        .collect()
}

/// Ordinal ranks of the `rank` transform (spec 3.4): 1 = highest. Ties are broken as numpy's
/// `flip(argsort(x))` with a stable sort breaks them: the later index ranks higher.
pub fn ordinal_rank(x: &[f64]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..x.len()).collect();
    order.sort_by(|&a, &b| x[a].total_cmp(&x[b]));
    let mut ranks = vec![0; x.len()];
    for (position, &index) in order.iter().rev().enumerate() {
        ranks[index] = position + 1;
    }
    ranks
}

/// Non-negative weights divided by their sum. Negative and NaN weights count as 0; if no weight is
/// positive the result is uniform; if some are infinite they share all the mass.
pub fn normalise(weights: &[f64]) -> Vec<f64> {
    let clean: Vec<f64> = weights
        .iter()
        .map(|&w| if w > 0.0 { w } else { 0.0 })
        .collect();
    let max = clean.iter().copied().fold(0.0, f64::max);
    if max == 0.0 {
        return vec![1.0 / clean.len() as f64; clean.len()];
    }
    let scaled: Vec<f64> = if max.is_infinite() {
        clean.iter().map(|&w| f64::from(w == max)).collect()
    } else {
        clean.iter().map(|&w| w / max).collect()
    };
    let total: f64 = scaled.iter().sum();
    scaled.iter().map(|&w| w / total).collect()
}

/// Probabilities from log weights, shifted by their maximum so nothing underflows to all zeros.
fn normalise_log(log_weights: &[f64]) -> Vec<f64> {
    let max = log_weights
        .iter()
        .copied()
        .fold(f64::NEG_INFINITY, f64::max);
    let weights: Vec<f64> = if max == f64::INFINITY {
        log_weights.iter().map(|&l| f64::from(l == max)).collect()
    } else {
        // With every log weight at -inf this is NaN everywhere, which `normalise` makes uniform.
        log_weights.iter().map(|&l| (l - max).exp()).collect()
    };
    normalise(&weights)
}

/// ln(v) for v > 0, -inf otherwise.
fn log_positive(v: f64) -> f64 {
    if v > 0.0 {
        v.ln()
    } else {
        f64::NEG_INFINITY
    }
}

/// An index drawn from the probability vector `probs` (by inversion of one uniform draw). An index
/// with probability 0 is never drawn.
pub fn draw<R: Rng + ?Sized>(probs: &[f64], rng: &mut R) -> usize {
    draw_with(probs, rng.random())
}

/// [`draw`] with the uniform number `u` in [0, 1) given.
pub fn draw_with(probs: &[f64], u: f64) -> usize {
    let mut cumulative = 0.0;
    for (index, &p) in probs.iter().enumerate() {
        cumulative += p;
        if u < cumulative {
            return index;
        }
    }
    // Rounding left the total just below u: take the last index that has mass.
    probs.iter().rposition(|&p| p > 0.0).unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn transform(kind: ScoreTransform) -> Transform {
        Transform {
            kind,
            temperature: 0.1,
            power_eps: 0.0,
        }
    }

    fn assert_close(actual: &[f64], expected: &[f64], tolerance: f64) {
        assert_eq!(actual.len(), expected.len());
        for (a, e) in actual.iter().zip(expected) {
            assert!((a - e).abs() <= tolerance, "{actual:?} != {expected:?}");
        }
    }

    #[test]
    fn rankmin_of_the_spec_example() {
        assert_eq!(rankmin(&[3.0, 2.0, 2.0, 1.0]), vec![2, 4, 4, 5]);
        // Weights 2^-10, 4^-10, 4^-10, 5^-10 normalised.
        let w = [
            2f64.powi(-10),
            4f64.powi(-10),
            4f64.powi(-10),
            5f64.powi(-10),
        ];
        let total: f64 = w.iter().sum();
        let expected: Vec<f64> = w.iter().map(|v| v / total).collect();
        let p = transform(ScoreTransform::Rankmin).probabilities(&[3.0, 2.0, 2.0, 1.0]);
        assert_close(&p, &expected, 1e-12);
        assert_close(&p, &[0.998, 0.001, 0.001, 0.0001], 5e-4);
    }

    #[test]
    fn rankmin_of_equal_values_is_uniform() {
        assert_eq!(rankmin(&[7.0; 3]), vec![4, 4, 4]);
        let p = transform(ScoreTransform::Rankmin).probabilities(&[7.0; 3]);
        assert_close(&p, &[1.0 / 3.0; 3], 1e-15);
    }

    #[test]
    fn ordinal_rank_breaks_ties_towards_the_later_index() {
        assert_eq!(ordinal_rank(&[3.0, 2.0, 2.0, 1.0]), vec![1, 3, 2, 4]);
        let p = transform(ScoreTransform::Rank).probabilities(&[1.0, 2.0]);
        let w2 = 2f64.powi(-10);
        assert_close(&p, &[w2 / (1.0 + w2), 1.0 / (1.0 + w2)], 1e-15);
    }

    #[test]
    fn constant_identity_power_softmax() {
        let x = [1.0, 3.0];
        assert_close(
            &transform(ScoreTransform::Constant).probabilities(&x),
            &[0.5, 0.5],
            1e-15,
        );
        assert_close(
            &transform(ScoreTransform::Identity).probabilities(&x),
            &[0.25, 0.75],
            1e-15,
        );
        let power = Transform {
            kind: ScoreTransform::Power,
            temperature: 0.5,
            power_eps: 1.0,
        };
        // (1+1)^2 = 4, (3+1)^2 = 16.
        assert_close(&power.probabilities(&x), &[0.2, 0.8], 1e-12);
        let softmax = Transform {
            kind: ScoreTransform::Softmax,
            temperature: 1.0,
            power_eps: 0.0,
        };
        let e2 = 2f64.exp();
        assert_close(
            &softmax.probabilities(&x),
            &[1.0 / (1.0 + e2), e2 / (1.0 + e2)],
            1e-12,
        );
    }

    #[test]
    fn underflowing_ranks_still_normalise() {
        // With β = 0.001 every raw weight rank^-1000 (ranks 2..1001) underflows to 0 in f64.
        let x: Vec<f64> = (0..1000).map(f64::from).collect();
        let sharp = Transform {
            kind: ScoreTransform::Rankmin,
            temperature: 0.001,
            power_eps: 0.0,
        };
        let p = sharp.probabilities(&x);
        assert_eq!(p[999], 1.0);
        assert!((p.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn degenerate_inputs_give_uniform_or_infinite_mass() {
        assert_close(&normalise(&[0.0, -1.0, f64::NAN]), &[1.0 / 3.0; 3], 1e-15);
        assert_close(&normalise(&[f64::INFINITY, 1.0]), &[1.0, 0.0], 0.0);
        let identity = transform(ScoreTransform::Identity);
        assert_close(&identity.probabilities(&[0.0, 0.0]), &[0.5, 0.5], 0.0);
        let softmax = transform(ScoreTransform::Softmax);
        assert_close(&softmax.probabilities(&[1e308, 0.0]), &[1.0, 0.0], 0.0);
        // NaN ranks last, as the lowest value would.
        let rankmin = transform(ScoreTransform::Rankmin);
        assert_eq!(
            rankmin.probabilities(&[f64::NAN, 1.0]),
            rankmin.probabilities(&[0.0, 1.0])
        );
    }

    #[test]
    fn draw_follows_the_probabilities_and_skips_zero_mass() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let probs = [0.0, 0.25, 0.0, 0.75];
        let mut counts = [0usize; 4];
        for _ in 0..20_000 {
            counts[draw(&probs, &mut rng)] += 1;
        }
        assert_eq!(counts[0] + counts[2], 0);
        let share = counts[3] as f64 / 20_000.0;
        assert!((share - 0.75).abs() < 0.02, "share of index 3: {share}");
    }
}
