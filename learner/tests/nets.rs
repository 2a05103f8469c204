//! Spec 5.1: initialisation statistics, the tanh-Gaussian policy, and the batched critic ensemble
//! against a naive per-member computation.
mod common;

use common::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::{MatmulPrecision, NetworkConfig, SacConfig};
use rfcl_learner::nets::{lecun_normal, orthogonal, squash_log_std, tanh_gaussian_log_prob};
use rfcl_learner::Sac;
use tch::{Kind, Tensor};

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// ‖M·Mᵀ − gain²·I‖∞ for an r×c row-major matrix (rows orthogonal).
fn row_gram_error(m: &[f64], r: usize, c: usize, gain: f64) -> f64 {
    let mut worst: f64 = 0.0;
    for i in 0..r {
        for j in 0..r {
            let dot: f64 = (0..c).map(|k| m[i * c + k] * m[j * c + k]).sum();
            let expected = if i == j { gain * gain } else { 0.0 };
            worst = worst.max((dot - expected).abs());
        }
    }
    worst
}

fn transpose(m: &[f64], r: usize, c: usize) -> Vec<f64> {
    (0..c)
        .flat_map(|j| (0..r).map(move |i| m[i * c + j]))
        .collect()
}

#[test]
fn orthogonal_init_has_orthonormal_columns_or_rows_times_gain() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    // Tall: columns orthonormal (WᵀW = g²I).
    let w = values(&orthogonal(&mut rng, 40, 16, 2f64.sqrt()));
    assert!(row_gram_error(&transpose(&w, 40, 16), 16, 40, 2f64.sqrt()) < 1e-12);
    // Wide: rows orthonormal (WWᵀ = g²I).
    let w = values(&orthogonal(&mut rng, 12, 30, 1.0));
    assert!(row_gram_error(&w, 12, 30, 1.0) < 1e-12);
    // Square: both.
    let w = values(&orthogonal(&mut rng, 20, 20, 2f64.sqrt()));
    assert!(row_gram_error(&w, 20, 20, 2f64.sqrt()) < 1e-12);
    assert!(row_gram_error(&transpose(&w, 20, 20), 20, 20, 2f64.sqrt()) < 1e-12);
}

#[test]
fn lecun_normal_is_truncated_at_two_std_with_variance_one_over_fan_in() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let fan_in = 64;
    let w = values(&lecun_normal(&mut rng, fan_in, 2000));
    let std = (1.0 / fan_in as f64).sqrt() / 0.879_625_661_034_239_8;
    assert!(w.iter().all(|x| x.abs() <= 2.0 * std));
    let mean = w.iter().sum::<f64>() / w.len() as f64;
    let var = w.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / w.len() as f64;
    assert!(mean.abs() < 0.01 * (1.0 / fan_in as f64).sqrt() * 10.0);
    let expected = 1.0 / fan_in as f64;
    assert!(
        (var - expected).abs() < 0.03 * expected,
        "var {var} vs {expected}"
    );
}

#[test]
fn agent_init_follows_spec_5_1() {
    let (sac_cfg, _) = small_config();
    let net = NetworkConfig::default();
    let cfg = SacConfig {
        critic_ensemble: 3,
        target_pool: 3,
        ..sac_cfg
    };
    let sac = Sac::with_kind(11, 3, &cfg, &net, 7, Kind::Double).unwrap();
    let actor = sac.actor_vars().variables();
    let critic = sac.critic_vars().variables();
    let sqrt2 = 2f64.sqrt();

    // Actor hidden layers: orthogonal √2; heads: orthogonal 1; every bias 0.
    let w = values(&actor["trunk0.kernel"]); // 11 × 256: rows orthonormal
    assert!(row_gram_error(&w, 11, 256, sqrt2) < 1e-9);
    let w = values(&actor["trunk1.kernel"]);
    assert!(row_gram_error(&w, 256, 256, sqrt2) < 1e-9);
    for head in ["mean", "log_std"] {
        let w = values(&actor[&format!("{head}.kernel")]); // 256 × 3: columns orthonormal
        assert!(row_gram_error(&transpose(&w, 256, 3), 3, 256, 1.0) < 1e-9);
    }
    for (name, t) in actor.iter().chain(critic.iter()) {
        if name.ends_with(".bias") {
            assert!(values(t).iter().all(|&x| x == 0.0), "{name} is not zero");
        }
    }

    // Critic: each member's first layer [14, 256] has orthonormal rows, members differ.
    let w = values(&critic["hidden0.kernel"]);
    let block = |e: usize| w[e * 14 * 256..(e + 1) * 14 * 256].to_vec();
    for e in 0..3 {
        assert!(row_gram_error(&block(e), 14, 256, sqrt2) < 1e-9);
    }
    assert!(max_abs_diff(&block(0), &block(1)) > 0.1);
    let hidden = values(&critic["hidden1.kernel"]);
    for e in 0..3 {
        assert!(row_gram_error(&hidden[e * 65536..(e + 1) * 65536], 256, 256, sqrt2) < 1e-9);
    }
    // LayerNorm scale 1, bias 0; output LeCun normal within ±2 std.
    assert!(values(&critic["norm2.scale"]).iter().all(|&x| x == 1.0));
    let bound = 2.0 * (1.0f64 / 256.0).sqrt() / 0.879_625_661_034_239_8;
    assert!(values(&critic["output.kernel"])
        .iter()
        .all(|x| x.abs() <= bound));
    // Target critic: an exact copy.
    let target = sac.target_critic_vars().variables();
    assert_eq!(target.len(), critic.len());
    for (name, t) in &target {
        assert_eq!(values(t), values(&critic[name]), "{name}");
    }
    // Temperature: log α = log(initial_temperature).
    assert_eq!(
        values(&sac.temperature_vars().variables()["log_alpha"]),
        vec![0.0]
    );
}

#[test]
fn log_std_squash_spans_min_to_max() {
    let h = Tensor::from_slice(&[-1e3, 0.0, 1e3]);
    assert_eq!(
        values(&squash_log_std(&h, -5.0, 2.0)),
        vec![-5.0, -1.5, 2.0]
    );
}

/// ∫₋₁¹ exp(log π(a)) da = 1 for the 1-D tanh-Gaussian (midpoint rule in a, u = atanh a).
#[test]
fn tanh_gaussian_density_integrates_to_one() {
    for (mean, log_std) in [
        (0.0, 0.0),
        (0.7, -1.0),
        (-1.2, 0.5),
        (2.0, -2.0),
        (0.0, -4.0),
    ] {
        let n = 400_000usize;
        let a: Vec<f64> = (0..n)
            .map(|i| -1.0 + (i as f64 + 0.5) * 2.0 / n as f64)
            .collect();
        let u = Tensor::from_slice(&a).atanh().unsqueeze(-1);
        let log_p = tanh_gaussian_log_prob(
            &u,
            &Tensor::from_slice(&[mean]).expand([n as i64, 1], false),
            &Tensor::from_slice(&[log_std]).expand([n as i64, 1], false),
        );
        let integral: f64 = values(&log_p).iter().map(|l| l.exp()).sum::<f64>() * 2.0 / n as f64;
        assert!(
            (integral - 1.0).abs() < 2e-3,
            "μ {mean} log σ {log_std}: ∫ = {integral}"
        );
    }
}

/// The stable correction equals the textbook log(1 − tanh² u) where the latter is accurate, and
/// stays finite where it is not.
#[test]
fn tanh_gaussian_log_prob_matches_textbook_form_and_is_stable() {
    let u = [-3.0, -0.5, 0.0, 0.25, 2.0];
    let (mean, log_std) = (0.3, -0.2);
    let got = values(&tanh_gaussian_log_prob(
        &Tensor::from_slice(&u).unsqueeze(-1),
        &Tensor::from_slice(&[mean; 5]).unsqueeze(-1),
        &Tensor::from_slice(&[log_std; 5]).unsqueeze(-1),
    ));
    for (i, &ui) in u.iter().enumerate() {
        let sigma: f64 = f64::exp(log_std);
        let z = (ui - mean) / sigma;
        let expected = -0.5 * z * z
            - log_std
            - 0.5 * (2.0 * std::f64::consts::PI).ln()
            - (1.0 - ui.tanh().powi(2)).ln();
        assert!(
            (got[i] - expected).abs() < 1e-12,
            "u {ui}: {} vs {expected}",
            got[i]
        );
    }
    // u = 30: 1 − tanh² u underflows to 0 in f32; the stable form does not.
    let far = tanh_gaussian_log_prob(
        &Tensor::from_slice(&[30.0f32]).unsqueeze(-1),
        &Tensor::from_slice(&[30.0f32]).unsqueeze(-1),
        &Tensor::from_slice(&[0.0f32]).unsqueeze(-1),
    );
    let v = values(&far)[0];
    let expected = -0.5 * (2.0 * std::f64::consts::PI).ln() + 2.0 * (30.0 - 2f64.ln());
    assert!(
        v.is_finite() && (v - expected).abs() < 1e-3,
        "{v} vs {expected}"
    );
}

#[test]
fn actor_matches_naive_computation_and_acts_deterministically_with_tanh_mean() {
    let (cfg, net) = small_config();
    let mut sac = Sac::with_kind(4, 3, &cfg, &net, 11, Kind::Double).unwrap();
    let naive = NaiveActor::from_vars(sac.actor_vars(), &net);
    let obs = pseudo_random(5 * 4, 1);
    let noise = pseudo_random(5 * 3, 2);
    let sample = sac
        .actor()
        .sample(&tensor(5, 4, &obs), &tensor(5, 3, &noise));
    let (actions, log_probs) = (values(&sample.action), values(&sample.log_prob));
    let deterministic = values(&sac.act_deterministic(&tensor(5, 4, &obs)));
    for r in 0..5 {
        let (a, lp) = naive.sample(&obs[r * 4..(r + 1) * 4], &noise[r * 3..(r + 1) * 3]);
        assert!(max_abs_diff(&actions[r * 3..(r + 1) * 3], &a) < 1e-12);
        assert!((log_probs[r] - lp).abs() < 1e-10);
        let (mean, _) = naive.gaussian(&obs[r * 4..(r + 1) * 4]);
        let tanh_mean: Vec<f64> = mean.iter().map(|m| m.tanh()).collect();
        assert!(max_abs_diff(&deterministic[r * 3..(r + 1) * 3], &tanh_mean) < 1e-12);
    }
    // Stochastic actions stay in (-1, 1).
    let acted = values(&sac.act(&tensor(5, 4, &obs)));
    assert!(acted.iter().all(|a| a.abs() < 1.0));
}

#[test]
fn critic_ensemble_matches_naive_per_member_loop() {
    for layer_norm in [true, false] {
        let (cfg, mut net) = small_config();
        net.critic_layer_norm = layer_norm;
        let sac = Sac::with_kind(4, 3, &cfg, &net, 13, Kind::Double).unwrap();
        let naive = naive_critics(sac.critic_vars(), &net, 4);
        let obs = pseudo_random(6 * 4, 3);
        let act = pseudo_random(6 * 3, 4);
        let q = sac
            .critic()
            .forward(&tensor(6, 4, &obs), &tensor(6, 3, &act));
        assert_eq!(q.size(), vec![4, 6]);
        let q = values(&q);
        for (e, member) in naive.iter().enumerate() {
            for r in 0..6 {
                let expected = member.q(&obs[r * 4..(r + 1) * 4], &act[r * 3..(r + 1) * 3]);
                assert!(
                    (q[e * 6 + r] - expected).abs() < 1e-12,
                    "member {e} row {r}"
                );
            }
        }
        // A selected sub-ensemble computes exactly those members.
        let picked = values(
            &sac.critic()
                .select(&[3, 1])
                .forward(&tensor(6, 4, &obs), &tensor(6, 3, &act)),
        );
        assert_eq!(picked[..6], q[18..24]);
        assert_eq!(picked[6..], q[6..12]);
    }
}

#[test]
fn bf16_matmuls_stay_close_to_fp32() {
    let (cfg, net) = small_config();
    let obs = pseudo_random(6 * 4, 8);
    let act = pseudo_random(6 * 3, 9);
    let fp32 = Sac::new(4, 3, &cfg, &net, 21).unwrap();
    let bf16_cfg = SacConfig {
        matmul_precision: MatmulPrecision::Bf16,
        ..cfg
    };
    let bf16 = Sac::new(4, 3, &bf16_cfg, &net, 21).unwrap();
    let (o, a) = (
        tensor(6, 4, &obs).to_kind(Kind::Float),
        tensor(6, 3, &act).to_kind(Kind::Float),
    );
    let q32 = values(&fp32.critic().forward(&o, &a));
    let q16 = values(&bf16.critic().forward(&o, &a));
    assert_ne!(q32, q16);
    assert!(max_abs_diff(&q32, &q16) < 0.05, "{q32:?} vs {q16:?}");
}
