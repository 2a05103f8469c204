use rfcl_core::config::{NetworkConfig, SacConfig};
use rfcl_learner::{Batch, Sac};
use std::time::Instant;
use tch::{Kind, Tensor};

fn time<F: FnMut()>(name: &str, n: usize, mut f: F) {
    f();
    let mut best = f64::MAX;
    for _ in 0..3 {
        let s = Instant::now();
        for _ in 0..n {
            f();
        }
        best = best.min(s.elapsed().as_secs_f64() / n as f64 * 1e3);
    }
    println!("{name:40} {best:8.3} ms");
}

fn main() {
    let threads: i32 = std::env::var("T").map(|t| t.parse().unwrap()).unwrap_or(1);
    rfcl_learner::runtime::configure_cpu(threads);
    let cfg = SacConfig::default();
    let net = NetworkConfig::default();
    let mut sac = Sac::new(42, 8, &cfg, &net, 0).unwrap();
    let b = 256;
    let mb = Batch {
        obs: Tensor::randn([b, 42], (Kind::Float, tch::Device::Cpu)),
        action: Tensor::rand([b, 8], (Kind::Float, tch::Device::Cpu)),
        reward: Tensor::rand([b], (Kind::Float, tch::Device::Cpu)),
        mask: Tensor::ones([b], (Kind::Float, tch::Device::Cpu)),
        next_obs: Tensor::randn([b, 42], (Kind::Float, tch::Device::Cpu)),
    };
    let noise = Tensor::randn([b, 8], (Kind::Float, tch::Device::Cpu));
    let params: Vec<Tensor> = sac.critic_vars().trainable_variables();
    let _ = 0;
    time("critic forward nograd", 20, || {
        let _ = tch::no_grad(|| sac.critic().forward(&mb.obs, &mb.action));
    });
    let _ = 0;
    time("critic forward grad", 20, || {
        let _ = sac.critic().forward(&mb.obs, &mb.action);
    });
    let _ = 0;
    time("target (actor + select + fwd)", 20, || {
        let _ = tch::no_grad(|| {
            let a = sac.actor().sample(&mb.next_obs, &noise);
            sac.target_critic()
                .select(&[1, 5])
                .forward(&mb.next_obs, &a.action)
        });
    });
    let _ = 0;
    time("critic loss", 20, || {
        let _ = sac.critic_loss(&mb, &[1, 5], &noise);
    });
    let _ = 0;
    time("critic loss + backward", 20, || {
        let (l, _) = sac.critic_loss(&mb, &[1, 5], &noise);
        Tensor::run_backward(&[l], &params, false, false);
    });
    let _ = 0;
    time("update_critic (incl adam+polyak)", 20, || {
        sac.update_critic(&mb);
    });
    let _ = 0;
    time("actor loss", 20, || {
        let _ = sac.actor_loss(&mb.obs, &noise);
    });
    let aparams: Vec<Tensor> = sac.actor_vars().trainable_variables();
    let _ = 0;
    time("actor loss + backward", 20, || {
        let (l, _) = sac.actor_loss(&mb.obs, &noise);
        Tensor::run_backward(&[l], &aparams, false, false);
    });
    let _ = 0;
    time("update_actor", 20, || {
        sac.update_actor(&mb.obs);
    });
    let pairs: Vec<(Tensor, Tensor)> = sac
        .target_critic_vars()
        .trainable_variables()
        .into_iter()
        .zip(sac.critic_vars().trainable_variables())
        .collect();
    let tv = sac.target_critic_vars().variables();
    let cv = sac.critic_vars().variables();
    let pairs: Vec<(Tensor, Tensor)> = tv
        .iter()
        .map(|(k, t)| (t.shallow_clone(), cv[k].shallow_clone()))
        .collect();
    time("polyak", 20, || {
        rfcl_learner::sac::polyak_update(&pairs, 0.005)
    });
    time("critic loss + backward + adam", 20, || {
        let (l, _) = sac.critic_loss(&mb, &[1, 5], &noise);
        let g = Tensor::run_backward(&[l], &sac.optimizers()[1].1.params(), false, false);
        sac.optimizers_mut()[1].1.step(g);
    });
    {
        use tch::nn::OptimizerConfig;
        let vs = sac.critic_vars();
        let cs: Vec<Tensor> = vs.trainable_variables().iter().map(|p| p.randn_like()).collect();
        let vars = vs.trainable_variables();
        let loss = || vars.iter().zip(&cs).map(|(p, c)| (p * c).sum(Kind::Float)).fold(Tensor::zeros([], (Kind::Float, tch::Device::Cpu)), |a, b| a + b);
        let mut theirs = tch::nn::Adam::default().build(vs, 1e-4).unwrap();
        time("tch Adam backward_step (critic)", 20, || theirs.backward_step(&loss()));
        let mut ours = rfcl_learner::adam::Adam::new(vs, 1e-4, 0.9, 0.999, 1e-8);
        time("our Adam minimize (critic)", 20, || ours.minimize(&loss()));
    }
    let (_, opt) = &mut sac.optimizers_mut()[1];
    let grads: Vec<Tensor> = opt.params().iter().map(|p| p.randn_like()).collect();
    let _ = 0;
    time("critic adam step", 20, || {
        opt.step(grads.iter().map(|g| g.copy()).collect());
    });
    let _ = 0;
    time("grad copies (baseline for adam)", 20, || {
        let _g: Vec<Tensor> = grads.iter().map(|g| g.copy()).collect();
    });
}
