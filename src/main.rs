//! `rfcl`: the local launcher and tools for RFCL runs.
//!
//! `rfcl train` runs the curriculum server, the learner and the actors of one run on this machine
//! ([`train`]); `rfcl eval` evaluates a run's exported policy ([`eval`]); the other subcommands
//! inspect and prepare what a run needs. Every subcommand that is not built yet says so and exits
//! non-zero.
#![forbid(unsafe_code)]

mod bench;
mod demos;
mod eval;
mod train;

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::{Parser, Subcommand};

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
        /// Run config (YAML), e.g. configs/pointmaze.yml; with --resume, the run's stored one is
        /// used (a CONFIG given then is only compared with it).
        #[arg(required_unless_present = "resume")]
        config: Option<PathBuf>,
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
        command: demos::DemosCommand,
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
        #[command(subcommand)]
        command: bench::BenchCommand,
    },
    /// Run configurations.
    Config {
        #[command(subcommand)]
        command: ConfigCommand,
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
            // With --resume, CONFIG may be left out: a first `key=value` is then an override.
            let (config, overrides) = match config {
                Some(c) if resume.is_some() && !c.exists() && c.to_string_lossy().contains('=') => {
                    let first = c.to_string_lossy().into_owned();
                    (None, [vec![first], overrides].concat())
                }
                c => (c, overrides),
            };
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
        Command::Demos { command } => demos::run(command),
        Command::Bench { command } => bench::run(command).map(|()| ExitCode::SUCCESS),
    }
}
