//! `rfcl`: the local launcher and tools for RFCL runs.
//!
//! `rfcl train` runs the curriculum server, the learner and the actors of one run on this machine;
//! the other subcommands inspect and prepare what a run needs. Every subcommand that is not built
//! yet says so and exits non-zero.
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "rfcl", version, about = "Reverse Forward Curriculum Learning as a distributed actor-learner service")]
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
        /// Continue a stopped run from its directory.
        #[arg(long, value_name = "RUN_DIR")]
        resume: Option<PathBuf>,
    },
    /// Demonstration datasets: generate, convert, inspect.
    Demos {
        #[command(subcommand)]
        command: DemosCommand,
    },
    /// Evaluate a run's exported policy on held-out seeds.
    Eval {
        run_dir: PathBuf,
        /// Episodes to run.
        #[arg(short = 'n', long, default_value_t = 100)]
        episodes: u32,
    },
    /// Benchmarks (results go to benches/RESULTS.md).
    Bench {
        /// What to measure: learner, curriculum, actor, e2e.
        target: String,
    },
    /// Run configurations.
    Config {
        #[command(subcommand)]
        command: ConfigCommand,
    },
}

#[derive(Subcommand)]
enum DemosCommand {
    /// Print episodes, lengths, dims, success flags and the state layout of a demo file.
    Inspect {
        /// ManiSkill-format trajectory file (.h5, with its .json sidecar).
        file: PathBuf,
    },
    /// Generate successful demos with their simulator states.
    Generate {
        /// Env: pointmaze, or a simulator env id such as PickCube-v1.
        #[arg(long)]
        env: String,
        /// Number of successful demos.
        #[arg(short = 'n', long, default_value_t = 5)]
        num: u32,
        /// Output .h5 file (a .json sidecar is written beside it).
        #[arg(long)]
        out: PathBuf,
        /// Seed of the first demo.
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Convert a trajectory file a user brings into the run's control mode and state observations.
    Convert {
        input: PathBuf,
        #[arg(long)]
        out: PathBuf,
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

fn main() -> ExitCode {
    tracing_subscriber::fmt().with_env_filter(tracing_subscriber::EnvFilter::from_default_env()).with_writer(std::io::stderr).init();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Config { command: ConfigCommand::Show { file, overrides } } => {
            let cfg = rfcl_core::config::resolve_file(&file, &overrides)?;
            print!("{}", rfcl_core::config::to_yaml(&cfg));
            Ok(())
        }
        Command::Demos { command: DemosCommand::Inspect { file } } => {
            let demos = rfcl_core::demo::DemoSet::load(&file)?;
            print!("{}", demos.summary());
            Ok(())
        }
        Command::Demos { command: DemosCommand::Generate { env, .. } } => {
            bail!("`rfcl demos generate --env {env}` is not built yet (issues 6 and 7)")
        }
        Command::Demos { command: DemosCommand::Convert { input, .. } } => {
            bail!("`rfcl demos convert {}` is not built yet (issues 7 and 8)", input.display())
        }
        Command::Train { config, .. } => {
            rfcl_core::config::resolve_file(&config, &[]).context("checking the config")?;
            bail!("`rfcl train` is not built yet (issue 6): the config resolves, but no run was started")
        }
        Command::Eval { run_dir, .. } => bail!("`rfcl eval {}` is not built yet (issue 6)", run_dir.display()),
        Command::Bench { target } => bail!("`rfcl bench {target}` is not built yet (issues 4 and 5)"),
    }
}
