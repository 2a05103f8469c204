//! The learner benchmark: full SAC updates per second on synthetic data, for `rfcl bench learner`
//! and `cargo bench -p rfcl-learner`, with the matmul FLOP count of each update.
//!
//! One "update" is one critic update plus its share 1/F of an actor and a temperature update, so
//! in the G16/F1 schedule it is one critic and one actor update (about 4.07 GFLOP with the
//! default networks, benches/RESULTS.md) and in G80/F20 a critic update plus 1/20 of an actor
//! update.
use crate::batch::HostBatch;
use crate::error::Result;
use crate::sac::Sac;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::{
    Backend, LearnerConfig, MatmulPrecision, NetworkConfig, Parallelism, SacConfig,
};
use serde::Serialize;
use std::time::{Duration, Instant};
use tch::Tensor;

/// What to measure.
#[derive(Debug, Clone, Serialize)]
pub struct BenchConfig {
    pub obs_dim: usize,
    pub action_dim: usize,
    pub batch_size: u32,
    pub hidden: Vec<u32>,
    pub critic_ensemble: u32,
    pub target_pool: u32,
    pub num_min_qs: u32,
    /// (G, F) pairs.
    pub schedules: Vec<(u32, u32)>,
    pub matmul_precision: MatmulPrecision,
    /// CPU threads of the updates, used as `parallelism` says (see
    /// [`crate::runtime::configure_cpu`] and [`Sac::set_member_threads`]).
    pub threads: i32,
    pub parallelism: Parallelism,
    /// How critic updates take their gradients (`learner.backend`).
    pub backend: Backend,
    /// Critic member shards with `members` parallelism (`None`: the learner's default,
    /// [`crate::members::SHARDS_PER_THREAD`] per thread).
    pub shards: Option<usize>,
    /// Untimed iterations before measuring, per schedule.
    pub warmup_iterations: u32,
    /// Timed windows per schedule; the best one is reported (the others are noise from whatever
    /// else the machine runs).
    pub windows: u32,
    /// Each window lasts at least this many seconds.
    pub window_seconds: f64,
    pub seed: u64,
}

impl Default for BenchConfig {
    /// The RFCL network (spec 8.1) on a ManiSkill-sized task: obs 42, action 8, batch 256,
    /// hidden 256×3, 10 critics, target min over 2 drawn from 10; G80/F20 and G16/F1.
    fn default() -> Self {
        Self {
            obs_dim: 42,
            action_dim: 8,
            batch_size: 256,
            hidden: vec![256, 256, 256],
            critic_ensemble: 10,
            target_pool: 10,
            num_min_qs: 2,
            schedules: vec![(80, 20), (16, 1)],
            matmul_precision: MatmulPrecision::Fp32,
            threads: 2,
            parallelism: Parallelism::Members,
            backend: Backend::Libtorch,
            shards: None,
            warmup_iterations: 1,
            windows: 3,
            window_seconds: 5.0,
            seed: 0,
        }
    }
}

/// The measurement of one schedule: its best window.
#[derive(Debug, Clone, Serialize)]
pub struct ScheduleResult {
    pub schedule: String,
    pub grad_updates_per_step: u32,
    pub actor_update_freq: u32,
    /// Iterations and seconds of the best window.
    pub iterations: u64,
    pub seconds: f64,
    /// Updates (critic update + 1/F actor update) per second.
    pub updates_per_s: f64,
    pub critic_updates_per_s: f64,
    pub actor_updates_per_s: f64,
    pub flop_per_update: f64,
    pub flop_per_critic_update: f64,
    pub flop_per_actor_update: f64,
    /// Achieved matmul GFLOP/s.
    pub gflop_per_s: f64,
    /// `gflop_per_s` over the report's `matmul_peak_gflop_per_s`.
    pub fraction_of_peak: f64,
    /// Seconds per iteration spent sampling and converting the batch (not in `seconds`).
    pub batch_seconds_per_iteration: f64,
    /// `updates_per_s` of every window, in order.
    pub window_updates_per_s: Vec<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    pub config: BenchConfig,
    pub device: String,
    /// The machine's measured fp32 matmul throughput at the same thread count (see
    /// [`matmul_peak_gflop_per_s`]), the yardstick for each result's `gflop_per_s`.
    pub matmul_peak_gflop_per_s: f64,
    pub results: Vec<ScheduleResult>,
}

/// Runs every schedule of `cfg` and returns the measurements (print them with `serde_json`).
pub fn run(cfg: &BenchConfig) -> Result<BenchReport> {
    // The yardstick is the GEMM peak with every thread on one op, whatever the parallelism.
    crate::runtime::configure_cpu(cfg.threads);
    let peak = matmul_peak_gflop_per_s(PEAK_GEMM_SIZE, cfg.window_seconds.min(2.0));
    let learner = LearnerConfig {
        parallelism: cfg.parallelism,
        ..LearnerConfig::default()
    };
    let (op_threads, member_threads) = learner.thread_split(cfg.threads.max(1) as u32);
    let runtime = crate::runtime::configure_cpu(op_threads as i32);
    let net = NetworkConfig {
        actor_features: cfg.hidden.clone(),
        critic_features: cfg.hidden.clone(),
        ..NetworkConfig::default()
    };
    let mut results = Vec::new();
    let mut shards_used = 1;
    for &(g, f) in &cfg.schedules {
        let sac_cfg = SacConfig {
            batch_size: cfg.batch_size,
            grad_updates_per_step: g,
            actor_update_freq: f,
            critic_ensemble: cfg.critic_ensemble,
            target_pool: cfg.target_pool,
            num_min_qs: cfg.num_min_qs,
            matmul_precision: cfg.matmul_precision,
            ..SacConfig::default()
        };
        let mut sac = Sac::new(cfg.obs_dim, cfg.action_dim, &sac_cfg, &net, cfg.seed)?;
        match cfg.shards {
            Some(shards) => sac.set_member_parallelism(member_threads as usize, shards),
            None => sac.set_member_threads(member_threads as usize),
        }
        sac.set_backend(cfg.backend);
        shards_used = if sac.member_threads() > 1 {
            sac.member_shards()
        } else {
            1
        };
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let rows = (g * cfg.batch_size) as usize;
        for _ in 0..cfg.warmup_iterations {
            let batch = random_batch(&mut rng, rows, cfg.obs_dim, cfg.action_dim);
            sac.train_iteration(&batch.to_tensors(sac.kind(), sac.device()))?;
        }
        let flops = Flops::new(cfg, &net);
        let flop_per_update = flops.critic_update + flops.actor_update / f64::from(f);
        let mut best: Option<ScheduleResult> = None;
        let mut window_rates = Vec::new();
        for _ in 0..cfg.windows.max(1) {
            let (mut iterations, mut busy, mut batch_time) = (0u64, Duration::ZERO, Duration::ZERO);
            while busy.as_secs_f64() < cfg.window_seconds {
                let start = Instant::now();
                let batch = random_batch(&mut rng, rows, cfg.obs_dim, cfg.action_dim)
                    .to_tensors(sac.kind(), sac.device());
                let prepared = Instant::now();
                sac.train_iteration(&batch)?;
                batch_time += prepared - start;
                busy += prepared.elapsed();
                iterations += 1;
            }
            let seconds = busy.as_secs_f64();
            let critic_updates = (iterations * u64::from(g)) as f64;
            let actor_updates = (iterations * u64::from(g / f)) as f64;
            let gflop_per_s = critic_updates * flop_per_update / seconds / 1e9;
            let window = ScheduleResult {
                schedule: format!("G{g}/F{f}"),
                grad_updates_per_step: g,
                actor_update_freq: f,
                iterations,
                seconds,
                updates_per_s: critic_updates / seconds,
                critic_updates_per_s: critic_updates / seconds,
                actor_updates_per_s: actor_updates / seconds,
                flop_per_update,
                flop_per_critic_update: flops.critic_update,
                flop_per_actor_update: flops.actor_update,
                gflop_per_s,
                fraction_of_peak: gflop_per_s / peak,
                batch_seconds_per_iteration: batch_time.as_secs_f64() / iterations as f64,
                window_updates_per_s: Vec::new(),
            };
            window_rates.push(window.updates_per_s);
            if best
                .as_ref()
                .is_none_or(|b| window.updates_per_s > b.updates_per_s)
            {
                best = Some(window);
            }
        }
        let mut best = best.expect("at least one window");
        best.window_updates_per_s = window_rates;
        results.push(best);
    }
    Ok(BenchReport {
        config: cfg.clone(),
        device: format!(
            "cpu, {} op threads x {member_threads} member threads ({} shards), allocator tuned: {}",
            runtime.threads, shards_used, runtime.allocator_tuned
        ),
        matmul_peak_gflop_per_s: peak,
        results,
    })
}

/// The square GEMM that measures the matmul peak: large enough that libtorch's BLAS reaches its
/// best rate, small enough to run a few times a second on 2 cores.
const PEAK_GEMM_SIZE: i64 = 1024;

/// fp32 GEMM throughput of libtorch on this machine with its current thread settings: the best of
/// repeated `[n, n] × [n, n]` products (2n³ FLOP each) for about `seconds`.
pub fn matmul_peak_gflop_per_s(n: i64, seconds: f64) -> f64 {
    let options = (tch::Kind::Float, tch::Device::Cpu);
    let (a, b) = (
        Tensor::randn([n, n], options),
        Tensor::randn([n, n], options),
    );
    let out = a.mm(&b); // warm-up (and the output buffer)
    let (start, mut best) = (Instant::now(), f64::INFINITY);
    while start.elapsed().as_secs_f64() < seconds || best.is_infinite() {
        let t = Instant::now();
        let _ = a.mm_out(&out, &b);
        best = best.min(t.elapsed().as_secs_f64());
    }
    gemm_gflop_per_s(n, best)
}

/// The rate of one `[n, n] × [n, n]` product (2n³ FLOP) that took `seconds`, in GFLOP/s.
fn gemm_gflop_per_s(n: i64, seconds: f64) -> f64 {
    2.0 * (n as f64).powi(3) / seconds / 1e9
}

/// Uniform random transitions in [-1, 1] (the maths do not care about the values).
fn random_batch(rng: &mut ChaCha8Rng, rows: usize, obs_dim: usize, action_dim: usize) -> HostBatch {
    let mut fill = |n: usize| {
        (0..n)
            .map(|_| rng.random_range(-1.0f32..1.0))
            .collect::<Vec<f32>>()
    };
    HostBatch {
        obs_dim,
        action_dim,
        obs: fill(rows * obs_dim),
        action: fill(rows * action_dim),
        reward: fill(rows),
        mask: vec![1.0; rows],
        next_obs: fill(rows * obs_dim),
    }
}

/// Matmul FLOPs (2 per multiply-add) of the updates; elementwise work is not counted.
#[derive(Debug, Clone, Copy)]
pub struct Flops {
    pub critic_update: f64,
    pub actor_update: f64,
}

impl Flops {
    pub fn new(cfg: &BenchConfig, net: &NetworkConfig) -> Self {
        let b = f64::from(cfg.batch_size);
        let (obs, act) = (cfg.obs_dim as f64, cfg.action_dim as f64);
        let e = f64::from(cfg.critic_ensemble);
        let k = f64::from(cfg.num_min_qs);
        // Multiply-adds per row of one network's forward pass, and of its first layer alone.
        let macs = |dims: &[f64]| dims.windows(2).map(|p| p[0] * p[1]).sum::<f64>();
        let widths = |f: &[u32]| f.iter().map(|&w| f64::from(w)).collect::<Vec<_>>();
        let mut actor_dims = vec![obs];
        actor_dims.extend(widths(&net.actor_features));
        let actor_fwd = macs(&actor_dims) + actor_dims.last().unwrap() * 2.0 * act;
        let actor_first = actor_dims[0] * actor_dims[1];
        let mut critic_dims = vec![obs + act];
        critic_dims.extend(widths(&net.critic_features));
        critic_dims.push(1.0);
        let critic_fwd = macs(&critic_dims);
        let critic_first = critic_dims[0] * critic_dims[1];

        let flop = |macs: f64| 2.0 * b * macs;
        // Target: actor at s′, k target members; online critic forward + weight grads of every
        // layer + input grads of every layer but the first.
        let critic_update =
            flop(actor_fwd + k * critic_fwd + e * (3.0 * critic_fwd - critic_first));
        // Actor forward, critic forward, critic input grads of every layer (down to the action),
        // actor weight grads of every layer + input grads of every layer but the first.
        let actor_update = flop(actor_fwd + e * 2.0 * critic_fwd + 2.0 * actor_fwd - actor_first);
        Self {
            critic_update,
            actor_update,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flops_of_the_rfcl_update_match_design_stack() {
        let cfg = BenchConfig::default();
        let net = NetworkConfig::default();
        let flops = Flops::new(&cfg, &net);
        // About 4.07 GFLOP for one critic + one actor update (benches/RESULTS.md: 4.065).
        assert_eq!(flops.critic_update + flops.actor_update, 4_065_067_008.0);
    }

    #[test]
    fn flops_hand_computed_case() {
        // obs 2, action 1, one hidden layer of 3, 2 critics, min over 1, batch 1:
        // critic 3→3→1 = 12 MACs (first layer 9); actor 2→3 + heads 3→2·1 = 12 MACs (first 6).
        let cfg = BenchConfig {
            obs_dim: 2,
            action_dim: 1,
            batch_size: 1,
            critic_ensemble: 2,
            num_min_qs: 1,
            ..BenchConfig::default()
        };
        let net = NetworkConfig {
            actor_features: vec![3],
            critic_features: vec![3],
            ..NetworkConfig::default()
        };
        let flops = Flops::new(&cfg, &net);
        assert_eq!(
            flops.critic_update,
            2.0 * (12.0 + 12.0 + 2.0 * (3.0 * 12.0 - 9.0))
        );
        assert_eq!(
            flops.actor_update,
            2.0 * (12.0 + 2.0 * 2.0 * 12.0 + 2.0 * 12.0 - 6.0)
        );
    }

    #[test]
    fn run_reports_every_schedule() {
        let cfg = BenchConfig {
            obs_dim: 3,
            action_dim: 2,
            batch_size: 8,
            hidden: vec![16],
            critic_ensemble: 3,
            target_pool: 3,
            schedules: vec![(4, 2), (2, 1)],
            threads: 1,
            windows: 2,
            window_seconds: 0.02,
            ..BenchConfig::default()
        };
        let report = run(&cfg).unwrap();
        let names: Vec<&str> = report.results.iter().map(|r| r.schedule.as_str()).collect();
        assert_eq!(names, ["G4/F2", "G2/F1"]);
        for r in &report.results {
            assert!(r.iterations >= 1 && r.seconds >= 0.02);
            assert_eq!(r.window_updates_per_s.len(), 2);
            assert!(r.window_updates_per_s.iter().all(|&w| w <= r.updates_per_s));
            let per_update = r.seconds / (r.iterations as f64 * f64::from(r.grad_updates_per_step));
            assert!((r.updates_per_s * per_update - 1.0).abs() < 1e-9);
            assert_eq!(
                r.actor_updates_per_s * f64::from(r.actor_update_freq),
                r.critic_updates_per_s
            );
        }
        let json = serde_json::to_value(&report).unwrap();
        assert!(json["results"][0]["flop_per_update"].as_f64().unwrap() > 0.0);
        assert!(report.matmul_peak_gflop_per_s > 0.0);
        for r in &report.results {
            let ratio = r.gflop_per_s / report.matmul_peak_gflop_per_s;
            assert!((r.fraction_of_peak - ratio).abs() < 1e-12);
        }
    }

    #[test]
    fn gemm_rate_hand_computed_case() {
        // 2·1000³ = 2e9 FLOP in 0.5 s: 4 GFLOP/s.
        assert!((gemm_gflop_per_s(1000, 0.5) - 4.0).abs() < 1e-12);
    }

    #[test]
    fn matmul_peak_measures_a_finite_rate() {
        // Only that a rate comes out: its size depends on the machine and its load (speed is
        // measured in benchmarks, never asserted in tests).
        let peak = matmul_peak_gflop_per_s(64, 0.01);
        assert!(peak.is_finite() && peak > 0.0, "{peak}");
    }
}
