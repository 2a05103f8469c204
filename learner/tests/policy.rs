//! The learner's side of the policy weights contract (rfcl-policy): the agent's actor, encoded,
//! is a policy that acts exactly like the agent, and the initial actor of a run is the policy
//! rfcl-policy initialises from the run seed.
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::{RunConfig, SacConfig};
use rfcl_learner::Sac;
use rfcl_policy::{encode_vars, PolicyNet, PolicyShape};
use tch::Tensor;

fn small() -> RunConfig {
    let mut cfg = RunConfig::default();
    cfg.network.actor_features = vec![8, 6];
    cfg.network.critic_features = vec![8];
    cfg.sac = SacConfig {
        critic_ensemble: 2,
        target_pool: 2,
        ..SacConfig::default()
    };
    cfg
}

#[test]
fn published_weights_act_like_the_agent() {
    let cfg = small();
    for seed in [0, 11] {
        let sac = Sac::new(5, 3, &cfg.sac, &cfg.network, seed).unwrap();
        let bytes = encode_vars(sac.actor_vars()).unwrap();
        let net = PolicyNet::from_safetensors(&bytes, &cfg, 5, 3).unwrap();
        let obs: Vec<f32> = (0..20).map(|i| (i as f32 * 0.37).sin()).collect();
        let ours = net.act_batch(&obs, true, &mut ChaCha8Rng::seed_from_u64(1));
        let theirs = Vec::<f32>::try_from(
            sac.act_deterministic(&Tensor::from_slice(&obs).view([4, 5]))
                .view([-1]),
        )
        .unwrap();
        assert_eq!(ours, theirs);
        assert_eq!(net.to_safetensors().unwrap(), bytes);
    }
}

#[test]
fn the_initial_actor_is_the_policy_of_the_run_seed() {
    let cfg = small();
    let shape = PolicyShape::from_config(&cfg, 5, 3);
    for seed in [0, 3] {
        let sac = Sac::new(5, 3, &cfg.sac, &cfg.network, seed).unwrap();
        assert_eq!(
            encode_vars(sac.actor_vars()).unwrap(),
            PolicyNet::init(shape.clone(), seed)
                .unwrap()
                .to_safetensors()
                .unwrap()
        );
    }
}
