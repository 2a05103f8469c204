//! Steps per second of a Python simulator env three ways (benches/RESULTS.md):
//!
//! * `raw`: the adapter stepped from a Python loop (the simulator's own rate);
//! * `in_process_pyo3`: each step a framed request through pyo3 in the same process (what an
//!   actor embedding Python would get);
//! * `worker_process`: [`PythonEnv`] driving an `rfcl-sim-worker` over pipes;
//! * `actor_rollout`: the same env inside the actor's [`Rollout`] (leases of 50 steps, sparse
//!   reward, transitions encoded into wire records) acting with the policy network of
//!   `configs/maniskill3/pick_cube.yml` (fresh weights, one libtorch thread): what an actor does.
//!
//! `cargo run --release -p rfcl-actor --example python_bridge_bench -- [ENV_ID] [STEPS]`
//! (default PickCube-v1, 3000 steps; uniform random actions, one episode of STEPS steps).
use std::process::Command;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rfcl_actor::env::Env;
use rfcl_actor::policy::PolicyHandle;
use rfcl_actor::python::{worker_program, PythonEnv, WorkerSpec};
use rfcl_actor::rollout::{Rollout, RolloutSettings, StepOutput};
use rfcl_core::lease::{LeaseKind, ResetArgs, ResetLease};
use rfcl_core::transition::RecordLayout;
use rfcl_policy::{PolicyNet, PolicyShape};

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let env_id = args.next().unwrap_or_else(|| "PickCube-v1".into());
    let steps: u32 = args.next().map_or(Ok(3000), |s| s.parse())?;
    let program = worker_program()?;

    let out = Command::new(&program)
        .args([
            "--suite",
            "maniskill3",
            "--env-id",
            &env_id,
            "--bench-steps",
            &steps.to_string(),
        ])
        .output()?;
    anyhow::ensure!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let in_process: serde_json::Value = serde_json::from_slice(&out.stdout)?;

    let spec = WorkerSpec {
        suite: "maniskill3".into(),
        env_id: env_id.clone(),
        options: serde_json::json!({}),
        program,
    };
    let mut env = PythonEnv::start(spec, 0)?;
    env.reset_to_seed(Some(0), &serde_json::json!({}))?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let actions: Vec<Vec<f32>> = (0..steps)
        .map(|_| {
            (0..env.action_dim())
                .map(|_| rng.random_range(-1.0..1.0))
                .collect()
        })
        .collect();
    let start = Instant::now();
    for a in &actions {
        env.step(a)?;
    }
    let worker = f64::from(steps) / start.elapsed().as_secs_f64();
    let actor = actor_rollout(env, steps)?;
    let raw = in_process["raw_steps_per_s"].as_f64().unwrap_or(f64::NAN);
    let pyo3 = in_process["in_process_pyo3_steps_per_s"]
        .as_f64()
        .unwrap_or(f64::NAN);
    println!(
        "{}",
        serde_json::to_string_pretty(&serde_json::json!({
            "env_id": env_id,
            "steps": steps,
            "raw_steps_per_s": raw,
            "in_process_pyo3_steps_per_s": pyo3,
            "worker_process_steps_per_s": worker,
            "worker_vs_in_process": worker / pyo3,
            "actor_rollout_steps_per_s": actor,
            "machine": { "cpus": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(0) },
        }))?
    );
    Ok(())
}

/// Steps per second of `env` inside a [`Rollout`] with the PickCube preset's policy network.
fn actor_rollout(env: PythonEnv, steps: u32) -> anyhow::Result<f64> {
    rfcl_actor::net::configure_inference_threads();
    let config = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../configs/maniskill3/pick_cube.yml"
    );
    let cfg = rfcl_core::config::resolve_file(std::path::Path::new(config), &[])?;
    let (obs_dim, action_dim) = (env.obs_dim(), env.action_dim());
    let net = PolicyNet::init(
        PolicyShape::from_config(&cfg, obs_dim, action_dim),
        cfg.seed,
    )?;
    let mut policy = PolicyHandle {
        version: 1,
        env_steps: 1,
        policy: Box::new(net),
    };
    let settings = RolloutSettings {
        actor_id: 0,
        num_seed_steps: 0,
        deterministic: false,
    };
    let mut rollout = Rollout::new(vec![Box::new(env)], 0, settings);
    let codec = RecordLayout::new(obs_dim, action_dim);
    let (mut wire, mut out, mut lease_id) = (Vec::new(), StepOutput::default(), 0u64);
    let (start, mut done) = (Instant::now(), 0u32);
    while done < steps {
        for env in rollout.idle_envs() {
            lease_id += 1;
            let lease = ResetLease {
                lease_id,
                kind: LeaseKind::Level,
                demo_id: 0,
                start_index: 0,
                env_state: Vec::new(),
                reset: ResetArgs {
                    seed: Some(lease_id),
                    options: serde_json::json!({}),
                },
                time_limit: 50,
                stage: 2,
                stage_epoch: 1,
                level: 0,
            };
            rollout.begin(env, lease)?;
        }
        out.clear();
        rollout.step(Some(&mut policy), &mut out)?;
        wire.resize(out.transitions.len() * codec.record_bytes(), 0);
        codec.encode_batch(&out.transitions, &mut wire)?;
        done += out.transitions.len() as u32;
    }
    Ok(f64::from(done) / start.elapsed().as_secs_f64())
}
