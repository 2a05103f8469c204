//! End to end: SAC (with its ensemble, replay and schedule) learns a sparse-reward 1-D reach task.
//!
//! The env: position x and goal g in [-1, 1], observation (x, g), action a in [-1, 1] moves
//! x ← clip(x + 0.25·a, −1, 1). Reward 1 on every step that ends within 0.1 of the goal (as RFCL's
//! sparse reward, spec 5.6: success never ends the episode, mask is always 1), horizon 20.
//! Success = within 0.1 of the goal at the last step, with the deterministic policy (spec 5.7).
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::{NetworkConfig, SacConfig};
use rfcl_learner::{Replay, ReplayBuffer, Sac};
use tch::{Kind, Tensor};

const HORIZON: usize = 20;

struct Reach {
    x: f32,
    goal: f32,
    t: usize,
}

impl Reach {
    fn reset(rng: &mut ChaCha8Rng) -> Self {
        Self {
            x: rng.random_range(-1.0..1.0),
            goal: rng.random_range(-1.0..1.0),
            t: 0,
        }
    }
    fn obs(&self) -> [f32; 2] {
        [self.x, self.goal]
    }
    fn success(&self) -> bool {
        (self.x - self.goal).abs() < 0.1
    }
    /// (reward, episode over)
    fn step(&mut self, action: f32) -> (f32, bool) {
        self.x = (self.x + 0.25 * action.clamp(-1.0, 1.0)).clamp(-1.0, 1.0);
        self.t += 1;
        (if self.success() { 1.0 } else { 0.0 }, self.t == HORIZON)
    }
}

fn success_rate(sac: &Sac, episodes: usize, seed: u64) -> f64 {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut successes = 0;
    for _ in 0..episodes {
        let mut env = Reach::reset(&mut rng);
        loop {
            let action = sac.act_deterministic(&Tensor::from_slice(&env.obs()).unsqueeze(0));
            let (_, done) = env.step(action.double_value(&[0, 0]) as f32);
            if done {
                break;
            }
        }
        successes += env.success() as usize;
    }
    successes as f64 / episodes as f64
}

#[test]
fn sac_learns_sparse_reward_reach() {
    tch::set_num_threads(1);
    let cfg = SacConfig {
        batch_size: 128,
        grad_updates_per_step: 2,
        actor_update_freq: 1,
        critic_ensemble: 4,
        target_pool: 4,
        num_min_qs: 2,
        discount: 0.9,
        tau: 0.01,
        actor_lr: 1e-3,
        critic_lr: 1e-3,
        temp_lr: 1e-3,
        ..SacConfig::default()
    };
    let net = NetworkConfig {
        actor_features: vec![64, 64],
        critic_features: vec![64, 64],
        ..NetworkConfig::default()
    };
    let mut sac = Sac::new(2, 1, &cfg, &net, 0).unwrap();
    let mut replay = Replay::new(ReplayBuffer::new("online", 20_000, 2, 1).unwrap(), None, 1);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let (seed_steps, steps, steps_per_iteration) = (1000, 5000, 2);

    let mut env = Reach::reset(&mut rng);
    for step in 0..steps {
        let obs = env.obs();
        let action = if step < seed_steps {
            rng.random_range(-1.0f32..1.0)
        } else {
            sac.act(&Tensor::from_slice(&obs).unsqueeze(0))
                .double_value(&[0, 0]) as f32
        };
        let (reward, done) = env.step(action);
        replay
            .online
            .push(&obs, &[action], reward, 1.0, &env.obs())
            .unwrap();
        if done {
            env = Reach::reset(&mut rng);
        }
        if step >= seed_steps && step % steps_per_iteration == 0 {
            let batch = replay
                .sample(cfg.grad_updates_per_step as usize, cfg.batch_size as usize)
                .unwrap();
            let metrics = sac
                .train_iteration(&batch.to_tensors(Kind::Float, sac.device()))
                .unwrap();
            assert!(metrics.critic_loss.is_finite() && metrics.actor_loss.is_finite());
        }
    }
    let rate = success_rate(&sac, 200, 99);
    assert!(rate > 0.95, "success rate {rate}");
}
