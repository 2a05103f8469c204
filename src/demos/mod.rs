//! `rfcl demos`: demonstration datasets, generated, recorded, converted, checked and selected.
//!
//! * [`check`]: `inspect`, run in a child process so that a file that crashes the HDF5 reader
//!   fails with a message instead of taking the launcher down.
//! * [`replay`]: the per-demo quality check (`inspect --replay`, `load`).
//! * [`select`]: `select`, the demos a run found hardest or easiest.
//! * [`sim`]: ManiSkill3 demos through the venv's Python (motion planners, conversion).
//! * [`suites`]: MetaWorld, Adroit and your own task's demos (scripted, converted, recorded).
pub mod check;
mod replay;
mod select;
pub mod sim;
mod suites;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::Subcommand;

/// `rfcl demos inspect --replay`: the per-demo quality check.
#[derive(clap::Args, Clone, Default)]
pub struct ReplayArgs {
    /// Check each demo in its simulator: every state is a valid reset state, its actions replayed
    /// from its first state reproduce its states and success flags, and its final state is a
    /// success. Exits 1 when a demo fails.
    #[arg(long)]
    pub replay: bool,
    /// The run config whose env replays the demos, or without --replay tries every state as a
    /// reset state (needed for every env but PointMaze).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

/// How many successful demos to write, and where: `generate`'s and `record`'s.
#[derive(clap::Args)]
pub struct DemoTarget {
    /// Number of successful demos.
    #[arg(short = 'n', long, default_value_t = 5)]
    pub num: u32,
    /// Output .h5 file (a .json sidecar is written beside it).
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Subcommand)]
pub enum DemosCommand {
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
        #[command(flatten)]
        target: DemoTarget,
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
        #[command(flatten)]
        target: DemoTarget,
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
        suite: suites::ConvertArgs,
    },
}

pub fn run(command: DemosCommand) -> Result<ExitCode> {
    match command {
        DemosCommand::Inspect { file, replay } => {
            let status = check::inspect(&file, &replay)?;
            Ok(ExitCode::from(
                status.code().unwrap_or(1).clamp(0, 255) as u8
            ))
        }
        DemosCommand::Select {
            file,
            run,
            out,
            best,
        } => select::select(&file, &run, &out, best).map(|()| ExitCode::SUCCESS),
        DemosCommand::Load { file, replay } => {
            let demos = rfcl_core::demo::DemoSet::load(&file)?;
            print!("{}", demos.summary());
            if !replay.replay {
                return Ok(
                    match replay::reset_states(&demos, replay.config.as_deref())? {
                        true => ExitCode::SUCCESS,
                        false => ExitCode::FAILURE,
                    },
                );
            }
            match replay::check(&demos, replay.config.as_deref())? {
                true => Ok(ExitCode::SUCCESS),
                false => Ok(ExitCode::FAILURE),
            }
        }
        DemosCommand::Generate { env, target, seed } => {
            generate(&env, target.num, &target.out, seed).map(|()| ExitCode::SUCCESS)
        }
        DemosCommand::Record {
            config,
            policy,
            target,
            seed,
            max_attempts,
        } => suites::record(
            &config,
            &policy,
            target.num,
            &target.out,
            seed,
            max_attempts,
        )
        .map(|()| ExitCode::SUCCESS),
        DemosCommand::Convert { input, out, suite } => {
            if suites::handles_convert(&input, &suite) {
                return suites::convert(&input, &out, &suite).map(|()| ExitCode::SUCCESS);
            }
            sim::convert(&input, &out).map(|()| ExitCode::SUCCESS)
        }
    }
}

pub fn generate(env: &str, num: u32, out: &Path, seed: u64) -> Result<()> {
    use rfcl_actor::pointmaze::{self, demos};
    if num == 0 {
        bail!("-n must be at least 1");
    }
    if sim::is_maniskill_env(env) {
        return sim::generate(env, num, out, seed);
    }
    if suites::is_suite_env(env) {
        return suites::generate(env, num, out, seed);
    }
    if !env.eq_ignore_ascii_case("pointmaze") && env != pointmaze::ENV_ID {
        bail!("`rfcl demos generate --env {env}` is not built yet: it takes pointmaze ({}) or a ManiSkill3 task with a motion planner ({}), or metaworld/<task> such as metaworld/pick-place-v3 (Adroit's demos are converted: `rfcl demos convert --help`)", pointmaze::ENV_ID, sim::MOTION_PLANNED.join(", "));
    }
    create_parent(out)?;
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

/// Creates the folder `out` goes in, when it names one.
fn create_parent(out: &Path) -> Result<()> {
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    Ok(())
}

/// `p` as UTF-8, for a Python tool's command line.
fn path_str(p: &Path) -> Result<&str> {
    p.to_str()
        .with_context(|| format!("{} is not valid UTF-8", p.display()))
}
