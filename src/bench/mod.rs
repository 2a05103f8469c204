//! `rfcl bench`: the benchmarks whose results go to benches/RESULTS.md, one subcommand each with
//! its own flags.
//!
//! * `curriculum`: Acquire + Report pairs over gRPC against the `curriculum-server` binary.
//! * `learner`: full SAC updates per second ([`rfcl_learner::bench`]).
//! * `actor`: the actor's overhead over a bare env loop ([`rfcl_actor::bench`]).
//! * `e2e`: env steps per second of whole `rfcl train` runs ([`e2e`]).
//! * `faults`: whole runs with a process killed, hung or its checkpoint damaged ([`faults`]).
mod e2e;
mod faults;

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Subcommand;
use rfcl_core::ready::ReadyLine;
use rfcl_proto::auth::{self, ClientAuth, Token};

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Acquire + Report pairs per second and their latency over gRPC, many concurrent clients.
    Curriculum {
        /// Concurrent clients.
        #[arg(long, default_value_t = 64)]
        clients: usize,
        /// Seconds of load.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
        /// Load this running curriculum server instead of starting one (e.g. http://127.0.0.1:50051).
        #[arg(long, value_name = "ADDR")]
        connect: Option<String>,
    },
    /// Full SAC updates per second on synthetic data, side by side per parallelism and backend.
    Learner {
        /// Seconds of measurement per setting.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
        #[command(flatten)]
        args: LearnerArgs,
    },
    /// The actor's overhead over a bare loop stepping the same PointMaze envs.
    Actor {
        /// Run config whose network the actor acts with.
        #[arg(long, default_value = "configs/pointmaze_test.yml")]
        config: PathBuf,
        /// Envs per actor.
        #[arg(long, default_value_t = 8)]
        envs: usize,
        /// Seconds of measurement.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
    },
    /// Env steps per second of whole `rfcl train` runs with 1, 2, 4 actors.
    E2e {
        /// Run config of the runs.
        #[arg(long, default_value = "configs/pointmaze_test.yml")]
        config: PathBuf,
        /// Actor counts, one whole run each.
        #[arg(long, value_delimiter = ',', default_value = "1,2,4")]
        actors: Vec<u32>,
        /// Seconds per run.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
    },
    /// Whole runs, the first undisturbed, the others each killing, hanging or damaging the
    /// checkpoint of one process at a random moment.
    Faults {
        /// Run config of the runs.
        #[arg(long, default_value = "configs/pointmaze_test.yml")]
        config: PathBuf,
        /// Whole runs, the first undisturbed.
        #[arg(long, default_value_t = 20)]
        runs: u32,
        /// What the disturbed runs do, in turn, each to every process kind it applies to.
        #[arg(long, value_enum, value_delimiter = ',', default_value = "kill")]
        faults: Vec<faults::Fault>,
        /// Seed of the fault moments.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Eval success at which each run stops.
        #[arg(long, default_value_t = 0.9)]
        bar: f64,
        /// Where the runs and their logs go.
        #[arg(long, default_value = "runs/bench-faults")]
        out: PathBuf,
    },
}

pub fn run(command: BenchCommand) -> Result<()> {
    match command {
        BenchCommand::Curriculum {
            clients,
            seconds,
            connect,
        } => curriculum(clients, seconds, connect),
        BenchCommand::Learner { seconds, args } => learner(seconds, &args),
        BenchCommand::Actor {
            config,
            envs,
            seconds,
        } => actor(&config, envs, seconds),
        BenchCommand::E2e {
            config,
            actors,
            seconds,
        } => {
            let results = e2e::run(&config, &actors, seconds)?;
            let json = serde_json::json!({
                "bench": "e2e_env_steps",
                "config": config,
                "seconds_per_run": seconds,
                "results": results,
                "machine": { "cpus": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(0) },
            });
            println!("{}", serde_json::to_string_pretty(&json)?);
            Ok(())
        }
        BenchCommand::Faults {
            config,
            runs,
            faults,
            seed,
            bar,
            out,
        } => {
            let results = faults::run(&config, runs, &faults, seed, bar, &out)?;
            let json = serde_json::json!({
                "bench": "faults",
                "config": config,
                "seed": seed,
                "bar": bar,
                "results": results,
            });
            println!("{}", serde_json::to_string_pretty(&json)?);
            println!("{}", faults::table(&results));
            Ok(())
        }
    }
}

/// The network and threads of `rfcl bench learner` (defaults: the RFCL network of spec 8.1 on a
/// ManiSkill-sized task, 2 threads, both parallelisms side by side).
#[derive(clap::Args)]
pub struct LearnerArgs {
    /// CPU threads of the updates
    #[arg(long, default_value_t = 2)]
    threads: u32,
    /// How the threads are used, one measurement each, side by side: members, ops.
    #[arg(long, value_delimiter = ',', default_value = "members,ops")]
    parallelism: Vec<String>,
    /// How critic updates take their gradients, one measurement each, side by side:
    /// libtorch (autograd), fused (docs/LEARNER.md "Backends").
    #[arg(long, value_delimiter = ',', default_value = "libtorch,fused")]
    backend: Vec<String>,
    /// Hidden layer widths of the actor and the critics
    #[arg(long, value_delimiter = ',', default_value = "256,256,256")]
    hidden: Vec<u32>,
    /// Critic member shards with `members` parallelism (default: one per thread).
    #[arg(long)]
    shards: Option<usize>,
    /// Critic ensemble size; the target minimum draws 2 from all of them
    #[arg(long, default_value_t = 10)]
    critics: u32,
    /// Observation and action dims, e.g. 39,4 for MetaWorld.
    #[arg(long, value_delimiter = ',', num_args = 1, default_value = "42,8")]
    dims: Vec<usize>,
}

/// Full SAC updates per second (rfcl_learner::bench; G80/F20 and G16/F1), best of 3 windows per
/// schedule within about `seconds`, once per parallelism asked for, side by side in one JSON
/// report. The side-by-side comparison with JAX is benches/compare_sac.sh.
fn learner(seconds: f64, args: &LearnerArgs) -> Result<()> {
    use rfcl_core::config::{Backend, Parallelism};
    let [obs_dim, action_dim] = args.dims[..] else {
        bail!(
            "--dims: expected OBS,ACTION (e.g. 39,4), got {:?}",
            args.dims
        );
    };
    let parallelisms = choose(
        "--parallelism",
        &args.parallelism,
        &[("members", Parallelism::Members), ("ops", Parallelism::Ops)],
    )?;
    let backends = choose(
        "--backend",
        &args.backend,
        &[("libtorch", Backend::Libtorch), ("fused", Backend::Fused)],
    )?;
    let mut reports = Vec::new();
    for (&parallelism, &backend) in parallelisms
        .iter()
        .flat_map(|p| backends.iter().map(move |b| (p, b)))
    {
        let cfg = rfcl_learner::bench::BenchConfig {
            window_seconds: (seconds / 6.0).max(1.0),
            threads: args.threads as i32,
            parallelism,
            backend,
            hidden: args.hidden.clone(),
            critic_ensemble: args.critics,
            target_pool: args.critics,
            obs_dim,
            action_dim,
            shards: args.shards,
            ..Default::default()
        };
        reports.push(rfcl_learner::bench::run(&cfg)?);
    }
    println!("{}", serde_json::to_string_pretty(&reports)?);
    Ok(())
}

/// The actor's overhead over a bare loop stepping the same PointMaze envs with the same network:
/// 4 alternating windows of `seconds / 8` each.
fn actor(config: &Path, envs: usize, seconds: f64) -> Result<()> {
    if envs == 0 {
        bail!("--envs must be at least 1");
    }
    let cfg = rfcl_core::config::resolve_file(config, &[])
        .with_context(|| format!("reading {}", config.display()))?;
    let window = std::time::Duration::from_secs_f64((seconds / 8.0).max(0.1));
    let result = rfcl_actor::bench::actor_overhead(&cfg, envs, window, 4)?;
    let json = serde_json::json!({
        "bench": "actor_overhead",
        "config": config,
        "result": result,
        "machine": { "cpus": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(0) },
    });
    println!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

/// Acquire + Report pairs against the `curriculum-server` binary on loopback, with PointMaze demos.
fn curriculum(clients: usize, seconds: f64, connect: Option<String>) -> Result<()> {
    use std::io::{BufRead, BufReader};
    use std::process::{Command, Stdio};
    let duration = std::time::Duration::from_secs_f64(seconds);
    // The load generator gets one worker thread, so that on a small machine it does not compete
    // with the server for every core (measured: p99 4.9 ms with 2 workers here, 3.8 ms with 1).
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    if let Some(addr) = connect {
        let auth = ClientAuth::from_env().context("calling the curriculum server")?;
        let result = rt.block_on(rfcl_curriculum::bench::acquire_report(
            &addr, &auth, clients, duration,
        ))?;
        println!(
            "{}",
            serde_json::to_string_pretty(
                &serde_json::json!({"bench": "curriculum_acquire_report", "server": addr, "result": result})
            )?
        );
        return Ok(());
    }
    let dir = tempfile::tempdir()?;
    let demos = dir.path().join("demos.h5");
    crate::demos::generate("pointmaze", 5, &demos, 0)?;
    let config = dir.path().join("bench.yml");
    // Snapshots as in a run; leases never expire during the bench.
    std::fs::write(&config, "name: bench\nenv:\n  suite: pointmaze\n  env_id: PointMaze-v0\nservice:\n  lease_timeout_s: 600\n")?;
    let server_bin = std::env::current_exe()?.with_file_name("curriculum-server");
    let token = Token::random();
    let mut child = Command::new(&server_bin)
        .args([
            "--demos",
            demos.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
            "--run-dir",
        ])
        .arg(dir.path().join("run"))
        .env("RUST_LOG", "warn")
        .env(auth::TOKEN_ENV, token.expose())
        .env_remove(auth::TOKEN_FILE_ENV)
        .stdout(Stdio::piped())
        .spawn()
        .with_context(|| format!("starting {}", server_bin.display()))?;
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line)?;
    let Some(addr) = ReadyLine::parse(&line).and_then(|ready| ready.grpc_url()) else {
        let _ = child.kill();
        bail!("curriculum-server did not start: {line:?}");
    };
    let auth = ClientAuth::plain(token);
    let result = rt.block_on(rfcl_curriculum::bench::acquire_report(
        &addr, &auth, clients, duration,
    ));
    let _ = child.kill();
    let _ = child.wait();
    let result = result?;
    let json = serde_json::json!({
        "bench": "curriculum_acquire_report",
        "result": result,
        "machine": { "cpus": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(0) },
    });
    println!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

/// Each of `names` as `choices` maps it, or an error naming `flag`, the name and the choices.
fn choose<T: Copy>(flag: &str, names: &[String], choices: &[(&str, T)]) -> Result<Vec<T>> {
    names
        .iter()
        .map(|name| match choices.iter().find(|(n, _)| n == name) {
            Some((_, value)) => Ok(*value),
            None => {
                let all: Vec<&str> = choices.iter().map(|(n, _)| *n).collect();
                bail!("{flag}: '{name}' is not one of {}", all.join(", "))
            }
        })
        .collect()
}
