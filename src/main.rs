//! `rfcl`: the local launcher and tools for RFCL runs.
//!
//! `rfcl train` runs the curriculum server, the learner and the actors of one run on this machine
//! ([`train`]); `rfcl eval` evaluates a run's exported policy ([`eval`]); the other subcommands
//! inspect and prepare what a run needs. Every subcommand that is not built yet says so and exits
//! non-zero.
#![forbid(unsafe_code)]

mod bench_e2e;
mod bench_faults;
mod demo_check;
mod demos_replay;
mod demos_select;
mod demos_sim;
mod demos_suites;
mod eval;
mod train;

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use rfcl_proto::auth::{self, ClientAuth, Token};

#[derive(Parser)]
#[command(
    name = "rfcl",
    version,
    about = "Reverse Forward Curriculum Learning as a distributed actor-learner service"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train a policy: start the curriculum server, the learner and the actors of one run.
    Train {
        /// Run config (YAML), e.g. configs/pointmaze.yml.
        config: PathBuf,
        /// Dotted overrides, e.g. `sac.batch_size=512`.
        overrides: Vec<String>,
        /// Continue a stopped run from its directory (its stored config.yml, plus the overrides
        /// given).
        #[arg(long, value_name = "RUN_DIR", conflicts_with = "run_dir")]
        resume: Option<PathBuf>,
        /// Run directory (default: runs/<name>, or runs/<name>-2, ... when that holds a run).
        #[arg(long, value_name = "DIR")]
        run_dir: Option<PathBuf>,
        /// libtorch threads of the learner's SAC updates; overrides `learner.threads` (default:
        /// all cores but one, which the actors and the curriculum server on this machine need).
        /// Written into the run's config.yml, so `--resume` keeps it.
        #[arg(long, value_name = "N")]
        learner_threads: Option<u32>,
    },
    /// Demonstration datasets: generate, convert, inspect.
    Demos {
        #[command(subcommand)]
        command: DemosCommand,
    },
    /// Evaluate a run's exported policy on held-out seeds (deterministic policy).
    Eval {
        /// A run directory with config.yml and policy.safetensors.
        run_dir: PathBuf,
        /// Episodes to run.
        #[arg(short = 'n', long, default_value_t = 100)]
        episodes: u32,
        /// Write each episode into this directory as an animated GIF from the simulator's own
        /// renderer (PointMaze: drawn by rfcl), named by its seed, success and return.
        #[arg(long, value_name = "DIR")]
        video: Option<PathBuf>,
    },
    /// Benchmarks (results go to benches/RESULTS.md).
    Bench {
        /// What to measure: curriculum (Acquire + Report pairs over gRPC), learner (SAC updates/s),
        /// actor (the actor's overhead over a bare env loop), e2e (whole runs, 1, 2, 4 actors) or
        /// faults (whole runs, each SIGKILLing one process at a random moment).
        target: String,
        /// Whole runs, the first undisturbed (faults).
        #[arg(long, default_value_t = 20)]
        runs: u32,
        /// Seed of the kill moments (faults).
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Eval success at which each run stops (faults).
        #[arg(long, default_value_t = 0.9)]
        bar: f64,
        /// Where the runs and their logs go (faults; default runs/bench-faults).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Concurrent clients (curriculum).
        #[arg(long, default_value_t = 64)]
        clients: usize,
        /// Seconds of load.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
        /// Load this running curriculum server instead of starting one (e.g. http://127.0.0.1:50051).
        #[arg(long, value_name = "ADDR")]
        connect: Option<String>,
        /// Run config whose network the actor bench acts with.
        #[arg(long, default_value = "configs/pointmaze_test.yml")]
        config: PathBuf,
        /// Envs per actor (actor).
        #[arg(long, default_value_t = 8)]
        envs: usize,
        /// Actor counts, one whole run each (e2e).
        #[arg(long, value_delimiter = ',', default_value = "1,2,4")]
        actors: Vec<u32>,
        #[command(flatten)]
        learner: LearnerBenchArgs,
    },
    /// Run configurations.
    Config {
        #[command(subcommand)]
        command: ConfigCommand,
    },
}

/// The network and threads of `rfcl bench learner` (defaults: the RFCL network of spec 8.1 on a
/// ManiSkill-sized task, 2 threads, both parallelisms side by side).
#[derive(clap::Args)]
struct LearnerBenchArgs {
    /// CPU threads of the updates (learner).
    #[arg(long, default_value_t = 2)]
    threads: u32,
    /// How the threads are used, one measurement each, side by side (learner): members, ops.
    #[arg(long, value_delimiter = ',', default_value = "members,ops")]
    parallelism: Vec<String>,
    /// How critic updates take their gradients, one measurement each, side by side (learner):
    /// libtorch (autograd), fused (docs/LEARNER.md "Backends").
    #[arg(long, value_delimiter = ',', default_value = "libtorch,fused")]
    backend: Vec<String>,
    /// Hidden layer widths of the actor and the critics (learner).
    #[arg(long, value_delimiter = ',', default_value = "256,256,256")]
    hidden: Vec<u32>,
    /// Critic member shards with `members` parallelism (learner; default: one per thread).
    #[arg(long)]
    shards: Option<usize>,
    /// Critic ensemble size; the target minimum draws 2 from all of them (learner).
    #[arg(long, default_value_t = 10)]
    critics: u32,
    /// Observation and action dims (learner), e.g. 39,4 for MetaWorld.
    #[arg(long, value_delimiter = ',', num_args = 1, default_value = "42,8")]
    dims: Vec<usize>,
}

/// `rfcl demos inspect --replay`: the per-demo quality check.
#[derive(clap::Args, Clone, Default)]
pub struct ReplayArgs {
    /// Check each demo in its simulator: every state is a valid reset state, its actions replayed
    /// from its first state reproduce its states and success flags, and its final state is a
    /// success. Exits 1 when a demo fails.
    #[arg(long)]
    pub replay: bool,
    /// The run config whose env replays the demos (needed for every env but PointMaze).
    #[arg(long, requires = "replay")]
    pub config: Option<PathBuf>,
}

#[derive(Subcommand)]
enum DemosCommand {
    /// Print episodes, lengths, dims, success flags and the state layout of a demo file.
    Inspect {
        /// ManiSkill-format trajectory file (.h5, with its .json sidecar).
        file: PathBuf,
        #[command(flatten)]
        replay: ReplayArgs,
    },
    /// Write the demo file without the demos a run found stalled (its dashboard's flags), or
    /// with only the best K (not stalled, solved, fastest frontier first), and say why each
    /// dropped demo went. The run may be running (its curriculum server is asked) or finished
    /// (its summary.json is read).
    Select {
        /// The demo file the run trained on.
        file: PathBuf,
        /// The run's directory (`rfcl train --run-dir`, by default runs/<name>).
        #[arg(long)]
        run: PathBuf,
        /// Output .h5 file (a .json sidecar is written beside it).
        #[arg(long)]
        out: PathBuf,
        /// Keep at most this many demos, the best first.
        #[arg(long)]
        best: Option<usize>,
    },
    /// `inspect` in this process, without the child that guards against libhdf5 crashing.
    #[command(hide = true)]
    Load {
        file: PathBuf,
        #[command(flatten)]
        replay: ReplayArgs,
    },
    /// Generate successful demos with their simulator states.
    Generate {
        /// Env: pointmaze, a ManiSkill3 env id such as PickCube-v1, or metaworld/<task> such as
        /// metaworld/pick-place-v3 (MetaWorld's scripted policies).
        #[arg(long)]
        env: String,
        /// Number of successful demos.
        #[arg(short = 'n', long, default_value_t = 5)]
        num: u32,
        /// Output .h5 file (a .json sidecar is written beside it).
        #[arg(long)]
        out: PathBuf,
        /// Seed of the generator (PointMaze: it orders the start cells after the three dead ends
        /// that the maze-covering demos always start from; MetaWorld: the first episode seed;
        /// ManiSkill3: the first motion-planning seed, the planner plans the seeds below it too and
        /// they are dropped).
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Record the successful episodes of your own policy (a Python callable from an observation
    /// to an action in [-1, 1]) in the env a run config describes, with their simulator states
    /// (docs/YOUR_TASK.md).
    Record {
        /// The run config whose env the policy acts in (its env.suite, env_id, env_kwargs,
        /// imports).
        #[arg(long)]
        config: PathBuf,
        /// The policy, module:callable (importable by the venv's Python, e.g. a module of a
        /// package in env.imports).
        #[arg(long)]
        policy: String,
        /// Number of successful demos.
        #[arg(short = 'n', long, default_value_t = 5)]
        num: u32,
        /// Output .h5 file (a .json sidecar is written beside it).
        #[arg(long)]
        out: PathBuf,
        /// First episode seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Episodes to try at most (default 4n).
        #[arg(long)]
        max_attempts: Option<u32>,
    },
    /// Convert a trajectory file a user brings into the run's control mode and state observations.
    Convert {
        input: PathBuf,
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        suite: demos_suites::ConvertArgs,
    },
}

#[derive(Subcommand)]
enum ConfigCommand {
    /// Print the fully resolved config (base configs and overrides applied, validated).
    Show {
        file: PathBuf,
        /// Dotted overrides, e.g. `sac.batch_size=512`.
        overrides: Vec<String>,
    },
}

/// The exit status of a training session stopped by Ctrl-C or SIGTERM (128 + SIGINT).
const EXIT_INTERRUPTED: u8 = 130;

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    run(Cli::parse()).unwrap_or_else(rfcl_runtime::fail)
}

fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::Train {
            config,
            overrides,
            resume,
            run_dir,
            learner_threads,
        } => {
            let summary = train::train(train::TrainArgs {
                config,
                overrides,
                resume,
                run_dir,
                learner_threads,
            })?;
            Ok(match summary.ending {
                train::progress::Ending::Interrupted => ExitCode::from(EXIT_INTERRUPTED),
                _ => ExitCode::SUCCESS,
            })
        }
        Command::Eval {
            run_dir,
            episodes,
            video,
        } => {
            let report = eval::eval(&run_dir, episodes, video.as_deref())?;
            println!(
                "{}: {} episodes from held-out seeds {}..: success {:.1}% at the end, {:.1}% \
                 once, mean return {:.2}, mean length {:.0}",
                report.env_id,
                report.episodes,
                report.first_seed,
                100.0 * report.success_at_end,
                100.0 * report.success_once,
                report.mean_return,
                report.mean_length
            );
            if report.env_id == rfcl_actor::pointmaze::ENV_ID {
                println!(
                    "success per start cell (tenths: 9 = 90% or more; G goal, # wall, X hazard wall):\n{}",
                    report.pointmaze_map()
                );
            }
            if let Some(dir) = &video {
                println!(
                    "{} videos (animated GIF) in {}",
                    report.videos.len(),
                    dir.display()
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Config {
            command: ConfigCommand::Show { file, overrides },
        } => {
            let cfg = rfcl_core::config::resolve_file(&file, &overrides)?;
            print!("{}", rfcl_core::config::to_yaml(&cfg));
            Ok(ExitCode::SUCCESS)
        }
        Command::Demos {
            command: DemosCommand::Inspect { file, replay },
        } => {
            let status = demo_check::inspect(&file, &replay)?;
            Ok(ExitCode::from(
                status.code().unwrap_or(1).clamp(0, 255) as u8
            ))
        }
        Command::Demos {
            command:
                DemosCommand::Select {
                    file,
                    run,
                    out,
                    best,
                },
        } => demos_select::select(&file, &run, &out, best).map(|()| ExitCode::SUCCESS),
        Command::Demos {
            command: DemosCommand::Load { file, replay },
        } => {
            let demos = rfcl_core::demo::DemoSet::load(&file)?;
            print!("{}", demos.summary());
            if !replay.replay {
                return Ok(match demos_replay::reset_states(&demos)? {
                    true => ExitCode::SUCCESS,
                    false => ExitCode::FAILURE,
                });
            }
            match demos_replay::check(&demos, replay.config.as_deref())? {
                true => Ok(ExitCode::SUCCESS),
                false => Ok(ExitCode::FAILURE),
            }
        }
        Command::Demos {
            command:
                DemosCommand::Generate {
                    env,
                    num,
                    out,
                    seed,
                },
        } => generate_demos(&env, num, &out, seed).map(|()| ExitCode::SUCCESS),
        Command::Demos {
            command:
                DemosCommand::Record {
                    config,
                    policy,
                    num,
                    out,
                    seed,
                    max_attempts,
                },
        } => demos_suites::record(&config, &policy, num, &out, seed, max_attempts)
            .map(|()| ExitCode::SUCCESS),
        Command::Demos {
            command: DemosCommand::Convert { input, out, suite },
        } => {
            if demos_suites::handles_convert(&input, &suite) {
                return demos_suites::convert(&input, &out, &suite).map(|()| ExitCode::SUCCESS);
            }
            demos_sim::convert(&input, &out).map(|()| ExitCode::SUCCESS)
        }
        Command::Bench {
            target,
            clients,
            seconds,
            connect,
            config,
            envs,
            actors,
            learner,
            runs,
            seed,
            bar,
            out,
        } => match target.as_str() {
            "curriculum" => bench_curriculum(clients, seconds, connect).map(|()| ExitCode::SUCCESS),
            "actor" => bench_actor(&config, envs, seconds).map(|()| ExitCode::SUCCESS),
            "learner" => bench_learner(seconds, &learner).map(|()| ExitCode::SUCCESS),
            "e2e" => {
                let results = bench_e2e::run(&config, &actors, seconds)?;
                let json = serde_json::json!({
                    "bench": "e2e_env_steps",
                    "config": config,
                    "seconds_per_run": seconds,
                    "results": results,
                    "machine": { "cpus": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(0) },
                });
                println!("{}", serde_json::to_string_pretty(&json)?);
                Ok(ExitCode::SUCCESS)
            }
            "faults" => {
                let out = out.unwrap_or_else(bench_faults::default_out);
                let results = bench_faults::run(&config, runs, seed, bar, &out)?;
                let json = serde_json::json!({
                    "bench": "faults",
                    "config": config,
                    "seed": seed,
                    "bar": bar,
                    "results": results,
                });
                println!("{}", serde_json::to_string_pretty(&json)?);
                println!("{}", bench_faults::table(&results));
                Ok(ExitCode::SUCCESS)
            }
            other => {
                bail!("`rfcl bench {other}`: expected curriculum, learner, actor, e2e or faults")
            }
        },
    }
}

fn generate_demos(env: &str, num: u32, out: &std::path::Path, seed: u64) -> Result<()> {
    use rfcl_actor::pointmaze::{self, demos};
    if demos_sim::is_maniskill_env(env) {
        return demos_sim::generate(env, num, out, seed);
    }
    if demos_suites::is_suite_env(env) {
        return demos_suites::generate(env, num, out, seed);
    }
    if !env.eq_ignore_ascii_case("pointmaze") && env != pointmaze::ENV_ID {
        bail!("`rfcl demos generate --env {env}` is not built yet: it takes pointmaze ({}) or a ManiSkill3 task with a motion planner ({}), or metaworld/<task> such as metaworld/pick-place-v3 (Adroit's demos are converted: `rfcl demos convert --help`)", pointmaze::ENV_ID, demos_sim::MOTION_PLANNED.join(", "));
    }
    if num == 0 {
        bail!("-n must be at least 1");
    }
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let set = demos::demo_set(demos::generate_demos(num as usize, seed), out);
    set.write(out)?;
    let lengths: Vec<usize> = set.demos.iter().map(|d| d.len()).collect();
    eprintln!(
        "wrote {num} successful PointMaze demos to {} (+ {}), lengths {lengths:?}",
        out.display(),
        rfcl_core::demo::DemoSet::sidecar_path(out).display()
    );
    Ok(())
}

/// Full SAC updates per second (rfcl_learner::bench; G80/F20 and G16/F1), best of 3 windows per
/// schedule within about `seconds`, once per parallelism asked for, side by side in one JSON
/// report. The side-by-side comparison with JAX is benches/compare_sac.sh.
fn bench_learner(seconds: f64, args: &LearnerBenchArgs) -> Result<()> {
    use rfcl_core::config::{Backend, Parallelism};
    let [obs_dim, action_dim] = args.dims[..] else {
        bail!(
            "--dims: expected OBS,ACTION (e.g. 39,4), got {:?}",
            args.dims
        );
    };
    let parallelisms = args
        .parallelism
        .iter()
        .map(|name| match name.as_str() {
            "members" => Ok(Parallelism::Members),
            "ops" => Ok(Parallelism::Ops),
            other => bail!("--parallelism: '{other}' is not one of members, ops"),
        })
        .collect::<Result<Vec<_>>>()?;
    let backends = args
        .backend
        .iter()
        .map(|name| match name.as_str() {
            "libtorch" => Ok(Backend::Libtorch),
            "fused" => Ok(Backend::Fused),
            other => bail!("--backend: '{other}' is not one of libtorch, fused"),
        })
        .collect::<Result<Vec<_>>>()?;
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
fn bench_actor(config: &std::path::Path, envs: usize, seconds: f64) -> Result<()> {
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
fn bench_curriculum(clients: usize, seconds: f64, connect: Option<String>) -> Result<()> {
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
    generate_demos("pointmaze", 5, &demos, 0)?;
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
    let addr = line
        .split("grpc=")
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .map(|a| format!("http://{a}"));
    let Some(addr) = addr else {
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
