//! Spec 5.2-5.3: each loss against an independent f64 computation, gradients against finite
//! differences, the target member draw, Polyak, Adam, and the update schedule.
mod common;

use common::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::SacConfig;
use rfcl_learner::adam::Adam;
use rfcl_learner::sac::{draw_target_members, temperature_loss};
use rfcl_learner::{Batch, LearnerError, Sac};
use std::collections::HashMap;
use tch::{nn, nn::OptimizerConfig, Kind, Tensor};

const OBS: usize = 4;
const ACT: usize = 3;

/// A minibatch of `rows` rows with mixed masks.
fn minibatch(rows: usize, seed: u64) -> (Batch, Vec<Vec<f64>>) {
    let obs = pseudo_random(rows * OBS, seed);
    let action: Vec<f64> = pseudo_random(rows * ACT, seed + 1)
        .iter()
        .map(|a| a * 0.9)
        .collect();
    let reward: Vec<f64> = pseudo_random(rows, seed + 2)
        .iter()
        .map(|r| (r > &0.0) as u8 as f64)
        .collect();
    let mask: Vec<f64> = (0..rows)
        .map(|i| if i % 3 == 2 { 0.0 } else { 1.0 })
        .collect();
    let next_obs = pseudo_random(rows * OBS, seed + 3);
    let batch = Batch {
        obs: tensor(rows, OBS, &obs),
        action: tensor(rows, ACT, &action),
        reward: Tensor::from_slice(&reward),
        mask: Tensor::from_slice(&mask),
        next_obs: tensor(rows, OBS, &next_obs),
    };
    (batch, vec![obs, action, reward, mask, next_obs])
}

/// An f64 agent whose target critic differs from its critic (one critic update done).
fn agent(cfg: &SacConfig, seed: u64) -> Sac {
    let (_, net) = small_config();
    let mut sac = Sac::with_kind(OBS, ACT, cfg, &net, seed, Kind::Double).unwrap();
    let (batch, _) = minibatch(cfg.batch_size as usize, 100);
    sac.update_critic(&batch);
    sac
}

fn all_params(sac: &Sac) -> HashMap<String, Vec<f64>> {
    rfcl_learner::checkpoint::network_tensors(sac)
        .into_iter()
        .map(|(name, t)| (name, values(&t)))
        .collect()
}

fn changed(
    before: &HashMap<String, Vec<f64>>,
    after: &HashMap<String, Vec<f64>>,
    prefix: &str,
) -> bool {
    before
        .iter()
        .filter(|(k, _)| k.starts_with(prefix))
        .any(|(k, v)| after[k] != *v)
}

#[test]
fn critic_loss_matches_independent_computation() {
    for backup_entropy in [false, true] {
        let (cfg, net) = small_config();
        let cfg = SacConfig {
            backup_entropy,
            ..cfg
        };
        let sac = agent(&cfg, 1);
        let rows = 6;
        let (batch, raw) = minibatch(rows, 7);
        let (obs, action, reward, mask, next_obs) = (&raw[0], &raw[1], &raw[2], &raw[3], &raw[4]);
        let members = [2i64, 0];
        let noise = pseudo_random(rows * ACT, 9);
        let (loss, q) = sac.critic_loss(&batch, &members, &tensor(rows, ACT, &noise));

        let actor = NaiveActor::from_vars(sac.actor_vars(), &net);
        let critics = naive_critics(sac.critic_vars(), &net, 4);
        let targets = naive_critics(sac.target_critic_vars(), &net, 4);
        let alpha = values(&sac.alpha())[0];
        let mut expected = 0.0;
        let q = values(&q);
        for r in 0..rows {
            let s2 = &next_obs[r * OBS..(r + 1) * OBS];
            let (a2, log_p) = actor.sample(s2, &noise[r * ACT..(r + 1) * ACT]);
            let mut v = members
                .iter()
                .map(|&k| targets[k as usize].q(s2, &a2))
                .fold(f64::INFINITY, f64::min);
            if backup_entropy {
                v -= alpha * log_p;
            }
            let y = reward[r] + cfg.discount * mask[r] * v;
            for (e, critic) in critics.iter().enumerate() {
                let qe = critic.q(
                    &obs[r * OBS..(r + 1) * OBS],
                    &action[r * ACT..(r + 1) * ACT],
                );
                assert!((q[e * rows + r] - qe).abs() < 1e-12);
                expected += (qe - y).powi(2);
            }
        }
        expected /= (rows * 4) as f64;
        let got = values(&loss)[0];
        // The textbook log(1 − tanh² u) of the naive actor loses ~1e-12 relative.
        assert!(
            (got - expected).abs() < 1e-10 * expected.abs(),
            "backup_entropy {backup_entropy}: {got} vs {expected}"
        );
    }
}

#[test]
fn actor_loss_matches_independent_computation() {
    let (cfg, net) = small_config();
    let mut sac = agent(&cfg, 2);
    // Move α off 1 so that it matters.
    sac.update_temperature(&Tensor::from(3.0f64));
    let rows = 6;
    let (_, raw) = minibatch(rows, 17);
    let obs = &raw[0];
    let noise = pseudo_random(rows * ACT, 19);
    let (loss, log_prob) = sac.actor_loss(&tensor(rows, OBS, obs), &tensor(rows, ACT, &noise));

    let actor = NaiveActor::from_vars(sac.actor_vars(), &net);
    let critics = naive_critics(sac.critic_vars(), &net, 4);
    let alpha = values(&sac.alpha())[0];
    assert!((alpha - 1.0).abs() > 1e-5);
    let log_prob = values(&log_prob);
    let mut expected = 0.0;
    for r in 0..rows {
        let s = &obs[r * OBS..(r + 1) * OBS];
        let (a, lp) = actor.sample(s, &noise[r * ACT..(r + 1) * ACT]);
        assert!((log_prob[r] - lp).abs() < 1e-10);
        let mean_q = critics.iter().map(|c| c.q(s, &a)).sum::<f64>() / 4.0;
        expected += alpha * lp - mean_q;
    }
    expected /= rows as f64;
    assert!((values(&loss)[0] - expected).abs() < 1e-12);
}

#[test]
fn temperature_loss_and_its_gradient() {
    let log_alpha = Tensor::from(0.3f64).set_requires_grad(true);
    let entropy = Tensor::from(-0.5f64);
    let loss = temperature_loss(&log_alpha, &entropy, -1.5);
    let alpha = 0.3f64.exp();
    assert!((values(&loss)[0] - alpha * (-0.5 + 1.5)).abs() < 1e-15);
    let grad = Tensor::run_backward(&[&loss], &[&log_alpha], false, false);
    // d/d log α of α (H − H̄) = α (H − H̄): entropy above target lowers α.
    assert!((values(&grad[0])[0] - alpha).abs() < 1e-15);

    // The default target entropy is −A/2 and the update moves α the right way.
    let (cfg, _) = small_config();
    let mut sac = agent(&cfg, 3);
    assert_eq!(sac.target_entropy(), -(ACT as f64) / 2.0);
    let before = values(&sac.alpha())[0];
    let step = sac.update_temperature(&Tensor::from(0.0f64)); // H = 0 > H̄ = −1.5
    assert_eq!(values(&step.temp)[0], before);
    let lowered = values(&sac.alpha())[0];
    assert!(lowered < before);
    sac.update_temperature(&Tensor::from(-5.0f64)); // H < H̄ raises α
    assert!(values(&sac.alpha())[0] > lowered);
}

/// Central finite differences of `loss` w.r.t. a few entries of every tensor in `vs`.
fn check_gradients(vs: &nn::VarStore, loss: &dyn Fn() -> Tensor) {
    let vars: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    let params: Vec<&Tensor> = vars.iter().map(|(_, t)| t).collect();
    let grads = Tensor::run_backward(&[loss()], &params, false, false);
    let named = vars.iter().map(|(n, _)| n.clone()).zip(grads).collect();
    check_against_finite_differences(vs, &|| values(&loss())[0], named, "autograd");
}

/// Each gradient in `grads` (by variable name) against central finite differences of `loss`, at
/// four entries of every variable of `vs`.
fn check_against_finite_differences(
    vs: &nn::VarStore,
    loss: &dyn Fn() -> f64,
    grads: HashMap<String, Tensor>,
    source: &str,
) {
    let h = 1e-6;
    let mut checked = 0;
    let vars = vs.variables();
    for (name, param) in &vars {
        let grad = values(&grads[name]);
        let n = grad.len();
        for i in [0, n / 3, n / 2, n - 1] {
            let entry = tch::no_grad(|| param.flatten(0, -1).get(i as i64));
            let original = values(&entry)[0];
            let at = |x: f64| {
                let _ = tch::no_grad(|| entry.shallow_clone().fill_(x));
                loss()
            };
            let fd = (at(original + h) - at(original - h)) / (2.0 * h);
            at(original);
            let tolerance = 1e-6 * (1.0 + fd.abs());
            assert!(
                (grad[i] - fd).abs() < tolerance,
                "{name}[{i}]: {source} {} vs finite difference {fd}",
                grad[i]
            );
            checked += 1;
        }
    }
    assert!(checked >= 4 * vars.len());
}

#[test]
fn critic_gradients_match_finite_differences() {
    let (cfg, _) = small_config();
    let sac = agent(&cfg, 4);
    let (batch, _) = minibatch(6, 27);
    let noise = tensor(6, ACT, &pseudo_random(6 * ACT, 29));
    check_gradients(sac.critic_vars(), &|| {
        sac.critic_loss(&batch, &[1, 2], &noise).0
    });
}

/// The fused backend's critic gradients (`learner.backend: fused`), against finite differences
/// of its own loss, which equals the libtorch path's (itself checked against an independent f64
/// computation above).
#[test]
fn fused_critic_gradients_match_finite_differences() {
    let (cfg, _) = small_config();
    let sac = agent(&cfg, 4);
    let (batch, _) = minibatch(6, 27);
    let noise = tensor(6, ACT, &pseudo_random(6 * ACT, 29));
    let target = sac.critic_target(&batch, &[1, 2], &noise);
    let fused = || {
        rfcl_learner::fused::critic_loss_and_grads(
            sac.critic(),
            &batch.obs,
            &batch.action,
            &target,
            1.0,
        )
        .expect("an f64 CPU critic takes the fused path")
    };
    let reference = values(&sac.critic_loss(&batch, &[1, 2], &noise).0)[0];
    let loss = values(&fused().loss)[0];
    assert!(
        (loss - reference).abs() < 1e-12 * reference.abs(),
        "{loss} vs {reference}"
    );
    let names = sac.critic().named_parameters().into_iter().map(|(n, _)| n);
    let grads = names.zip(fused().grads).collect();
    check_against_finite_differences(
        sac.critic_vars(),
        &|| values(&fused().loss)[0],
        grads,
        "fused",
    );
}

#[test]
fn actor_gradients_match_finite_differences() {
    let (cfg, _) = small_config();
    let sac = agent(&cfg, 5);
    let (batch, _) = minibatch(6, 37);
    let noise = tensor(6, ACT, &pseudo_random(6 * ACT, 39));
    check_gradients(sac.actor_vars(), &|| sac.actor_loss(&batch.obs, &noise).0);
}

#[test]
fn each_update_changes_only_its_own_parameters() {
    let (cfg, _) = small_config();
    let mut sac = agent(&cfg, 6);
    let (batch, _) = minibatch(6, 47);

    let before = all_params(&sac);
    let critic_before: HashMap<String, Tensor> = sac
        .critic_vars()
        .variables()
        .into_iter()
        .map(|(k, v)| (k, v.copy()))
        .collect();
    let target_before: HashMap<String, Tensor> = sac
        .target_critic_vars()
        .variables()
        .into_iter()
        .map(|(k, v)| (k, v.copy()))
        .collect();
    sac.update_critic(&batch);
    let after = all_params(&sac);
    assert!(changed(&before, &after, "critic/") && changed(&before, &after, "target/"));
    assert!(!changed(&before, &after, "actor/") && !changed(&before, &after, "temperature/"));
    // Polyak after the critic step: θ̄ ← (1 − τ) θ̄ + τ θ.
    let critic_now = sac.critic_vars().variables();
    for (name, target) in sac.target_critic_vars().variables() {
        let expected = &target_before[&name] * (1.0 - cfg.tau) + &critic_now[&name] * cfg.tau;
        let diff = (target - expected).abs().max().double_value(&[]);
        assert!(diff < 1e-15, "{name}: {diff}");
        assert!(
            critic_before[&name]
                .not_equal_tensor(&critic_now[&name])
                .any()
                .int64_value(&[])
                == 1
        );
    }

    let before = after;
    let step = sac.update_actor(&batch.obs);
    let after = all_params(&sac);
    assert!(changed(&before, &after, "actor/"));
    assert!(!changed(&before, &after, "critic/") && !changed(&before, &after, "target/"));
    assert!(!changed(&before, &after, "temperature/"));

    let before = after;
    sac.update_temperature(&step.entropy);
    let after = all_params(&sac);
    assert!(changed(&before, &after, "temperature/"));
    assert!(!changed(&before, &after, "actor/") && !changed(&before, &after, "critic/"));
}

#[test]
fn target_members_are_distinct_within_the_pool_and_seeded() {
    let mut a = ChaCha8Rng::seed_from_u64(9);
    let mut b = ChaCha8Rng::seed_from_u64(9);
    let mut pairs = std::collections::HashSet::new();
    let mut counts = [0usize; 10];
    for _ in 0..20_000 {
        let drawn = draw_target_members(&mut a, 10, 2);
        assert_eq!(drawn, draw_target_members(&mut b, 10, 2));
        assert_eq!(drawn.len(), 2);
        assert_ne!(drawn[0], drawn[1]);
        assert!(drawn.iter().all(|&m| (0..10).contains(&m)));
        pairs.insert((drawn[0].min(drawn[1]), drawn[0].max(drawn[1])));
        drawn.iter().for_each(|&m| counts[m as usize] += 1);
    }
    assert_eq!(pairs.len(), 45, "every unordered pair of 10 appears");
    for c in counts {
        assert!(
            (c as f64 - 4000.0).abs() < 300.0,
            "member frequency {c} vs 4000"
        );
    }
    // The reference's wall-time MS configs: pool {0, 1}, both always drawn.
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for _ in 0..10 {
        let mut drawn = draw_target_members(&mut rng, 2, 2);
        drawn.sort();
        assert_eq!(drawn, vec![0, 1]);
    }
    let other: Vec<_> = (0..5)
        .map(|_| draw_target_members(&mut ChaCha8Rng::seed_from_u64(10), 10, 2))
        .collect();
    assert!(other.iter().all(|d| d == &other[0]));
}

/// `train_iteration` = R rounds of F critic updates, then actor + temperature on the round's last
/// minibatch: replaying that sequence by hand on an identically seeded agent gives bit-identical
/// parameters and the same metrics.
#[test]
fn train_iteration_follows_the_schedule_of_spec_5_2() {
    let (cfg, _) = small_config(); // G 4, F 2, B 6
    let (g, f, b) = (4, 2, 6);
    let (batch, _) = minibatch(g * b, 57);
    let mut scheduled = agent(&cfg, 8);
    let mut manual = agent(&cfg, 8);

    let metrics = scheduled.train_iteration(&batch).unwrap();

    let (mut critic_loss, mut actor_loss, mut entropy) = (0.0, 0.0, 0.0);
    for round in 0..g / f {
        for k in 0..f {
            let mb = batch.minibatch((round * f + k) as i64, b as i64).unwrap();
            critic_loss += values(&manual.update_critic(&mb).loss)[0];
        }
        let last = batch
            .minibatch((round * f + f - 1) as i64, b as i64)
            .unwrap();
        let step = manual.update_actor(&last.obs);
        actor_loss += values(&step.loss)[0];
        entropy += values(&step.entropy)[0];
        manual.update_temperature(&step.entropy);
    }
    assert_eq!(all_params(&scheduled), all_params(&manual));
    assert!((metrics.critic_loss - critic_loss / g as f64).abs() < 1e-12);
    assert!((metrics.actor_loss - actor_loss / (g / f) as f64).abs() < 1e-12);
    assert!((metrics.entropy - entropy / (g / f) as f64).abs() < 1e-12);
    assert_eq!((metrics.critic_updates, metrics.actor_updates), (4, 2));
    let steps: Vec<i64> = scheduled
        .optimizers()
        .iter()
        .map(|(_, o)| o.step_count())
        .collect();
    assert_eq!(steps, vec![2, 4 + 1, 2]); // actor, critic (+1 in `agent`), temperature

    let tags: Vec<&str> = metrics.tagged().iter().map(|(t, _)| *t).collect();
    assert_eq!(
        tags,
        [
            "train/critic/critic_loss",
            "train/critic/q",
            "train/actor/actor_loss",
            "train/actor/entropy",
            "train/temp/temp",
            "train/temp/temp_loss"
        ]
    );
    // A batch of the wrong size is refused.
    assert!(matches!(
        scheduled.train_iteration(&minibatch(6, 1).0),
        Err(LearnerError::Shape(_))
    ));
}

/// The member-parallel updates (`set_member_threads`) compute the batched updates' maths: after
/// several training iterations with 4 critics on 1-4 threads and 2-4 shards (2+2, 2+1+1,
/// 1+1+1+1 members), every parameter, optimiser state and metric agrees to float rounding.
#[test]
fn member_threads_give_the_batched_updates() {
    let (cfg, _) = small_config(); // G 4, F 2, B 6, 4 critics
    let (batch, _) = minibatch(4 * 6, 91);
    let mut reference = agent(&cfg, 21);
    assert_eq!(reference.member_threads(), 1);
    let expected: Vec<_> = (0..3)
        .map(|_| reference.train_iteration(&batch).unwrap())
        .collect();
    // (threads, shards): one shard per thread, the default shards per thread, more shards than
    // threads, and more threads than members.
    for (threads, shards) in [(2, 2), (2, 0), (3, 3), (2, 3), (4, 4), (9, 9)] {
        let mut sharded = agent(&cfg, 21);
        if shards == 0 {
            sharded.set_member_threads(threads);
        } else {
            sharded.set_member_parallelism(threads, shards);
        }
        assert_eq!(sharded.member_threads(), threads.min(4));
        for want in &expected {
            let got = sharded.train_iteration(&batch).unwrap();
            for ((tag, a), (_, b)) in got.tagged().iter().zip(want.tagged().iter()) {
                assert!(
                    (a - b).abs() < 1e-12,
                    "{threads} threads, {tag}: {a} vs {b}"
                );
            }
        }
        let (want, got) = (all_params(&reference), all_params(&sharded));
        for (name, w) in &want {
            let g = &got[name];
            let diff = w
                .iter()
                .zip(g)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max);
            assert!(
                diff < 1e-12,
                "{threads} threads, {name}: max difference {diff}"
            );
        }
        for ((name, a), (_, b)) in reference
            .optimizers()
            .iter()
            .zip(sharded.optimizers().iter())
        {
            for ((key, x), (_, y)) in a.state().iter().zip(b.state().iter()) {
                let diff = (x - y).abs().max().double_value(&[]);
                assert!(diff < 1e-12, "{threads} threads, {name} {key}: {diff}");
            }
        }
    }
}

/// The fused CPU backend (`learner.backend: fused`) takes the same updates as libtorch's
/// autograd: three training iterations (critic, actor and temperature updates) from one seed
/// give the same metrics, parameters and optimiser states in f64, up to summation order, on the
/// calling thread and split over member threads.
#[test]
fn the_fused_backend_takes_libtorchs_updates() {
    use rfcl_core::config::Backend;
    let (cfg, _) = small_config(); // G 4, F 2, B 6, 4 critics
    let (batch, _) = minibatch(4 * 6, 93);
    for threads in [1, 2] {
        let mut reference = agent(&cfg, 23);
        let mut fused = agent(&cfg, 23);
        reference.set_backend(Backend::Libtorch);
        reference.set_member_threads(threads);
        fused.set_member_threads(threads);
        fused.set_backend(Backend::Fused);
        for _ in 0..3 {
            let (want, got) = (
                reference.train_iteration(&batch).unwrap(),
                fused.train_iteration(&batch).unwrap(),
            );
            for ((tag, a), (_, b)) in got.tagged().iter().zip(want.tagged().iter()) {
                assert!(
                    (a - b).abs() < 1e-10,
                    "{threads} threads, {tag}: {a} vs {b}"
                );
            }
        }
        let (want, got) = (all_params(&reference), all_params(&fused));
        for (name, w) in &want {
            let diff = w
                .iter()
                .zip(&got[name])
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max);
            assert!(
                diff < 1e-10,
                "{threads} threads, {name}: max difference {diff}"
            );
        }
        for ((name, a), (_, b)) in reference.optimizers().iter().zip(fused.optimizers().iter()) {
            for ((key, x), (_, y)) in a.state().iter().zip(b.state().iter()) {
                let diff = (x - y).abs().max().double_value(&[]);
                assert!(diff < 1e-10, "{threads} threads, {name} {key}: {diff}");
            }
        }
    }
}

#[test]
fn fixed_temperature_stays_put() {
    let (cfg, _) = small_config();
    let cfg = SacConfig {
        learnable_temp: false,
        initial_temperature: 0.2,
        ..cfg
    };
    let mut sac = agent(&cfg, 9);
    sac.update_temperature(&Tensor::from(5.0f64));
    assert!((values(&sac.alpha())[0] - 0.2).abs() < 1e-15);
}

#[test]
fn adam_matches_libtorch_adam() {
    let make = || {
        let mut vs = nn::VarStore::new(tch::Device::Cpu);
        vs.set_kind(Kind::Double);
        let root = vs.root();
        let _ = root.var_copy("w", &tensor(3, 4, &pseudo_random(12, 1)));
        let _ = root.var_copy("b", &Tensor::from_slice(&pseudo_random(4, 2)));
        vs
    };
    let (ours_vs, theirs_vs) = (make(), make());
    let mut ours = Adam::new(&ours_vs, 1e-2, 0.9, 0.999, 1e-8);
    let mut theirs = nn::Adam {
        beta1: 0.9,
        beta2: 0.999,
        wd: 0.0,
        eps: 1e-8,
        amsgrad: false,
    }
    .build(&theirs_vs, 1e-2)
    .unwrap();
    for step in 0..20u64 {
        // loss = Σ c ⊙ p² with step-dependent c.
        let loss = |vs: &nn::VarStore| {
            let v = vs.variables();
            let c = tensor(3, 4, &pseudo_random(12, 10 + step));
            (&c * v["w"].square()).sum(Kind::Double)
                + (v["b"].square() * (step as f64 - 7.0)).sum(Kind::Double)
        };
        ours.minimize(&loss(&ours_vs));
        theirs.backward_step(&loss(&theirs_vs));
    }
    let (o, t) = (ours_vs.variables(), theirs_vs.variables());
    for name in ["w", "b"] {
        let diff = (&o[name] - &t[name]).abs().max().double_value(&[]);
        assert!(diff < 1e-12, "{name}: {diff}");
    }
    assert_eq!(ours.step_count(), 20);

    // The state round-trips.
    let state = ours.state();
    let fresh_vs = make();
    let mut fresh = Adam::new(&fresh_vs, 1e-2, 0.9, 0.999, 1e-8);
    fresh.load_state(&state).unwrap();
    assert_eq!(fresh.step_count(), 20);
    for ((n1, t1), (n2, t2)) in fresh.state().iter().zip(&state) {
        assert_eq!(n1, n2);
        assert_eq!(values(t1), values(t2));
    }
}

#[test]
fn impossible_configs_are_refused() {
    let (cfg, net) = small_config();
    let bad = [
        SacConfig {
            actor_update_freq: 3,
            ..cfg.clone()
        },
        SacConfig {
            num_min_qs: 4,
            ..cfg.clone()
        },
        SacConfig {
            target_pool: 5,
            ..cfg.clone()
        },
        SacConfig {
            critic_ensemble: 0,
            ..cfg.clone()
        },
        SacConfig {
            initial_temperature: 0.0,
            ..cfg.clone()
        },
    ];
    for c in bad {
        assert!(
            matches!(
                Sac::new(OBS, ACT, &c, &net, 0),
                Err(LearnerError::Config(_))
            ),
            "{c:?}"
        );
    }
    assert!(Sac::new(OBS, ACT, &cfg, &net, 0).is_ok());
}

/// The learner moves the agent and the replay into its training thread.
#[test]
fn agent_and_replay_are_send() {
    fn assert_send<T: Send>() {}
    assert_send::<Sac>();
    assert_send::<rfcl_learner::Replay>();
    assert_send::<Batch>();
}

/// Stepping an ensemble's optimiser slice by slice (as member threads do) is one Adam step: with
/// a constant gradient g, m̂ = g and v̂ = g² at every step, so each step moves a parameter by
/// −lr · g / (|g| + ε) ≈ −lr · sign(g), by hand.
#[test]
fn adam_slices_take_the_whole_step() {
    let mut vs = nn::VarStore::new(tch::Device::Cpu);
    vs.set_kind(Kind::Double);
    let w = vs
        .root()
        .var_copy("w", &tensor(2, 2, &[1.0, 2.0, 3.0, 4.0]));
    let mut adam = Adam::new(&vs, 0.1, 0.9, 0.999, 1e-8);
    let grad = tensor(2, 2, &[0.5, -2.0, 4.0, -0.25]);
    for _ in 0..2 {
        let step = adam.begin_step();
        // Member 1 first: the slices are independent.
        for member in [1, 0] {
            adam.slice(member, 1)
                .step(step, vec![grad.narrow(0, member, 1).copy()]);
        }
    }
    assert_eq!(adam.step_count(), 2);
    for (got, want) in values(&w).iter().zip([0.8, 2.2, 2.8, 4.2]) {
        assert!((got - want).abs() < 1e-6, "{got} vs {want}");
    }
}

/// Every parameter of `sac` under `prefix` (see [`all_params`]).
fn params_under(sac: &Sac, prefix: &str) -> HashMap<String, Vec<f64>> {
    all_params(sac)
        .into_iter()
        .filter(|(k, _)| k.starts_with(prefix))
        .collect()
}

#[test]
fn reinitialise_starts_only_the_chosen_parts_afresh() {
    let (cfg, net) = small_config();
    let mut sac = agent(&cfg, 8);
    let (batch, _) = minibatch(6, 48);
    let step = sac.update_actor(&batch.obs);
    sac.update_temperature(&step.entropy);
    let fresh = Sac::with_kind(OBS, ACT, &cfg, &net, 99, Kind::Double).unwrap();
    let steps = |sac: &Sac| sac.optimizers().map(|(_, opt)| opt.step_count());
    assert_eq!(steps(&sac), [1, 1, 1]);

    // load_actor false: the actor is the fresh one, the critics and α are untouched.
    let trained = all_params(&sac);
    sac.reinitialise(true, false, &net, 99).unwrap();
    let now = all_params(&sac);
    assert_eq!(params_under(&sac, "actor/"), params_under(&fresh, "actor/"));
    assert!(changed(&trained, &now, "actor/"));
    for part in ["critic/", "target/", "temperature/"] {
        assert!(!changed(&trained, &now, part), "{part}");
    }
    assert_eq!(steps(&sac), [0, 1, 1]);

    // load_critic false: critics, target (a copy of them) and α are the fresh ones.
    sac.reinitialise(false, true, &net, 99).unwrap();
    for part in ["actor/", "critic/", "temperature/"] {
        assert_eq!(
            params_under(&sac, part),
            params_under(&fresh, part),
            "{part}"
        );
    }
    let strip = |m: HashMap<String, Vec<f64>>, prefix: &str| -> HashMap<String, Vec<f64>> {
        m.into_iter()
            .map(|(k, v)| (k[prefix.len()..].to_string(), v))
            .collect()
    };
    assert_eq!(
        strip(params_under(&sac, "target/"), "target/"),
        strip(params_under(&fresh, "critic/"), "critic/")
    );
    assert_eq!(steps(&sac), [0, 0, 0]);

    // The Polyak pairs still join the (reinitialised) target to the critics.
    let before = all_params(&sac);
    sac.update_critic(&batch);
    let after = all_params(&sac);
    assert!(changed(&before, &after, "critic/") && changed(&before, &after, "target/"));
    assert_eq!(steps(&sac), [0, 1, 0]);
}
