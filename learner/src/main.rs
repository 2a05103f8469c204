//! `learner`: ensemble SAC on libtorch with replay, gRPC transition ingest, policy publication,
//! stage transitions and checkpoints (docs/LEARNER.md).
//!
//! ```text
//! learner --config CFG [key=value ...] --curriculum http://ADDR [--demos FILE] [--run-dir DIR]
//!         [--port P] [--bind 127.0.0.1] [--resume RUN_DIR] [--device cpu|cuda] [--threads N]
//!         [--metrics-port P]
//! ```
//!
//! On start it loads the config and the demos (spec 6.1 selection), subscribes to the curriculum
//! server's stage announcements, builds the agent and the buffers (or restores them with
//! `--resume`), binds gRPC and prints exactly one line on stdout:
//! `learner ready grpc=127.0.0.1:PORT` (with ` metrics=http://ADDR/metrics` when
//! `--metrics-port` is given). Logs go to stderr. It stops after `train.steps` env steps,
//! when the curriculum server ends the run, or on SIGINT/SIGTERM, each time with a final
//! checkpoint and the exported policy (exit 0); a failure exits non-zero with a one-line error.
//! The service itself is `rfcl_learner::server`; this binary loads, binds and calls it.
use std::net::IpAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Parser;
use rfcl_core::config::{Device, RunConfig, StagePlan};
use rfcl_core::demo::DemoSet;
use rfcl_learner::checkpoint::{self, Manifest};
use rfcl_learner::server::{Bound, Inputs, Server};
use rfcl_learner::stages;
use rfcl_learner::trainer::Trainer;
use rfcl_proto::auth::{ClientAuth, ServerAuth};
use tokio::sync::mpsc;

#[derive(Parser)]
#[command(
    name = "learner",
    version,
    about = "RFCL learner: ensemble SAC on libtorch, replay, ingest, policy publication"
)]
struct Args {
    /// Run config (YAML). With --resume, defaults to the config the checkpoint was written under.
    #[arg(long, required_unless_present = "resume")]
    config: Option<PathBuf>,
    /// Curriculum server address, e.g. http://127.0.0.1:50051.
    #[arg(long)]
    curriculum: String,
    /// Demo file (ManiSkill-format .h5 with its .json sidecar); default: train.dataset_path.
    #[arg(long)]
    demos: Option<PathBuf>,
    /// Run directory (checkpoints, metrics.csv, exported policy); default `runs/<name>`.
    #[arg(long, value_name = "RUN_DIR")]
    run_dir: Option<PathBuf>,
    /// Continue from the checkpoint in this run directory.
    #[arg(long, value_name = "RUN_DIR", conflicts_with = "run_dir")]
    resume: Option<PathBuf>,
    /// gRPC port for actors (0 = a free one; the address is printed on stdout).
    #[arg(long, default_value_t = 0)]
    port: u16,
    /// Serve Prometheus `/metrics` on this port (0 = a free one; the URL is on the ready line).
    /// Default: no metrics endpoint.
    #[arg(long, value_name = "P")]
    metrics_port: Option<u16>,
    /// Address to bind the gRPC (and metrics) port on.
    #[arg(long, default_value = "127.0.0.1")]
    bind: IpAddr,
    /// The URL at which the curriculum server reaches this learner's gRPC, for its dashboard's
    /// learner panel, e.g. http://learner:50052. Default: the bound address (this host's name
    /// when bound to 0.0.0.0 or ::).
    #[arg(long, value_name = "URL", env = "RFCL_LEARNER_ADVERTISE")]
    advertise: Option<String>,
    /// Where the SAC updates run (overrides sac.device).
    #[arg(long, value_parser = ["cpu", "cuda"])]
    device: Option<String>,
    /// libtorch CPU threads for the SAC maths (overrides learner.threads; default: all cores
    /// but one, at least 1).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=4096))]
    threads: Option<u32>,
    /// Capacity of the ingest queue, in transition batches (bounded: back-pressure beyond it).
    #[arg(long, default_value_t = 8)]
    queue_batches: usize,
    /// Serve no shared-memory services: every actor, on this host too, uses gRPC.
    #[arg(long)]
    no_shm: bool,
    /// Seconds to wait for the curriculum server at start.
    #[arg(long, default_value_t = 10.0)]
    connect_timeout_s: f64,
    /// Dotted config overrides, e.g. `sac.batch_size=128`.
    overrides: Vec<String>,
}

fn main() -> ExitCode {
    // Before any thread starts, so that every thread shares the one tuned arena.
    rfcl_learner::runtime::tune_allocator();
    // A damaged demo file can crash libhdf5: read once in a child copy of this binary first.
    rfcl_runtime::isolated::serve_if_child(|file| {
        DemoSet::load(file).map(drop).map_err(Into::into)
    });
    rfcl_runtime::init_logging();
    let args = Args::parse();
    rfcl_runtime::run(rfcl_runtime::Flavor::Workers(2), run(args))
}

async fn run(args: Args) -> Result<()> {
    // Installed first: a signal during start-up is handled, not fatal.
    let mut signals = rfcl_runtime::Signals::install()?;
    // Every call needs the run's token (and TLS when configured), ours to the curriculum server
    // too: read before anything else so a missing token fails at once.
    let server_auth = ServerAuth::from_env().context("the learner's gRPC service")?;
    let client_auth = ClientAuth::from_env().context("calling the curriculum server")?;
    let manifest = match (&args.resume, &args.run_dir) {
        (Some(dir), _) => Some(
            checkpoint::read_manifest(&checkpoint::checkpoint_dir(dir))?.with_context(|| {
                format!(
                    "--resume {}: no learner checkpoint in {}",
                    dir.display(),
                    checkpoint::checkpoint_dir(dir).display()
                )
            })?,
        ),
        (None, Some(dir)) => checkpoint::read_manifest(&checkpoint::checkpoint_dir(dir))?,
        (None, None) => None,
    };
    let cfg = load_config(&args, manifest.as_ref())?;
    let run_dir = args
        .resume
        .clone()
        .or(args.run_dir.clone())
        .unwrap_or_else(|| PathBuf::from("runs").join(&cfg.name));
    // A learner that finds its own checkpoint in its run directory continues it (a restarted
    // container, a supervisor's restart): the run goes on without anyone passing --resume.
    // (An explicit --run-dir or --resume was read above, before the config.)
    let manifest = match manifest {
        None if args.run_dir.is_none() && args.resume.is_none() => {
            checkpoint::read_manifest(&checkpoint::checkpoint_dir(&run_dir))?
        }
        m => m,
    };
    if args.resume.is_none() {
        if let Some(m) = &manifest {
            tracing::info!(
                generation = m.generation,
                env_steps = m.progress.env_steps,
                "found a learner checkpoint in {}: resuming from it",
                run_dir.display()
            );
        }
    }
    let demos = load_demos(&args, &cfg)?;
    std::fs::create_dir_all(&run_dir)
        .with_context(|| format!("creating the run directory {}", run_dir.display()))?;
    // Held until the process ends: a second learner on this directory is refused before it
    // writes anything.
    let _lock = rfcl_core::run_lock::RunDirLock::acquire(&run_dir, "learner")?;
    let ckpt_dir = checkpoint::checkpoint_dir(&run_dir);
    let mut member_threads = 1;
    if cfg.sac.device == Device::Cpu {
        let threads = cfg.learner.threads_here(args.threads);
        let (op_threads, members) = cfg.learner.thread_split(threads);
        let applied = rfcl_learner::runtime::configure_cpu(op_threads as i32);
        member_threads = members as usize;
        tracing::info!(
            threads,
            parallelism = ?cfg.learner.parallelism,
            backend = ?cfg.learner.backend,
            op_threads = applied.threads,
            member_threads,
            "SAC updates on the CPU"
        );
        if cfg.sac.matmul_precision == rfcl_core::config::MatmulPrecision::Bf16 {
            match rfcl_learner::runtime::native_bf16().as_slice() {
                [] => tracing::warn!(
                    "sac.matmul_precision is bf16 but this CPU has neither AMX nor AVX512-BF16: libtorch emulates bf16 products, slower than fp32 (docs/LEARNER.md, \"bf16 matmuls\")"
                ),
                native => tracing::info!(?native, "bf16 matmuls run natively"),
            }
        }
        if applied.threads > 1 && std::env::var_os("OMP_WAIT_POLICY").is_none() {
            tracing::info!(
                "OMP_WAIT_POLICY is not set: OpenMP threads spin while idle; set OMP_WAIT_POLICY=PASSIVE when actors share these cores (docs/LEARNER.md, \"Threads\")"
            );
        }
    }

    let timeout = Duration::from_secs_f64(args.connect_timeout_s.max(0.1));
    let (stage_stream, first_stage) = stages::open(&args.curriculum, &client_auth, timeout, "")
        .await
        .context("subscribing to the curriculum server's stage announcements")?;
    tracing::info!(
        stage = first_stage.stage.number(),
        epoch = first_stage.epoch,
        "curriculum server at {}",
        args.curriculum
    );

    let (trainer, policy_rx, status) = match &manifest {
        Some(m) => {
            if first_stage.epoch < m.progress.stage_epoch {
                bail!(
                    "the curriculum server is at stage epoch {} but the learner checkpoint at {}: resume the curriculum server from the same run directory",
                    first_stage.epoch,
                    m.progress.stage_epoch
                );
            }
            let resumed = Trainer::resume(cfg.clone(), &demos, run_dir.clone(), m)
                .with_context(|| format!("resuming from {}", ckpt_dir.display()))?;
            tracing::info!(
                env_steps = m.progress.env_steps,
                critic_updates = m.progress.critic_updates,
                policy_version = m.progress.policy_version,
                online = m.online.len,
                "resumed from checkpoint generation {} in {}",
                m.generation,
                ckpt_dir.display()
            );
            resumed
        }
        None => {
            if first_stage.epoch > 0
                && !matches!(cfg.train.stage_plan(), Ok(StagePlan::ForwardOnly))
            {
                tracing::warn!(
                    "the curriculum server is already at stage epoch {}: a fresh learner starts there with the demos as its offline buffer",
                    first_stage.epoch
                );
            }
            Trainer::fresh(cfg.clone(), &demos, run_dir.clone(), &first_stage)
                .context("building the agent and the replay")?
        }
    };
    let mut trainer = trainer;
    trainer.set_member_threads(member_threads);
    trainer.set_backend(cfg.learner.backend);

    let bound = Bound::bind(args.bind, args.port, args.metrics_port).await?;
    let server = Server::start(
        bound,
        Inputs {
            cfg,
            run_dir,
            trainer,
            policy: policy_rx,
            status,
            curriculum: args.curriculum.clone(),
            first_stage,
            stage_stream,
            connect_timeout: timeout,
            advertise: args.advertise.clone(),
            queue_batches: args.queue_batches,
            shm: !args.no_shm,
            server_auth,
            client_auth,
        },
    )?;
    println!("{}", server.ready_line());
    // Each signal is a stop request: the first finishes with a final checkpoint, a second aborts.
    let (stop_tx, stop_rx) = mpsc::unbounded_channel();
    tokio::spawn(async move {
        loop {
            signals.recv().await;
            if stop_tx.send(()).is_err() {
                break;
            }
        }
    });
    server.serve(stop_rx).await
}

/// The run config: `--config` with the overrides, or (resuming without `--config`) the config the
/// checkpoint was written under. `--device` overrides `sac.device`.
fn load_config(args: &Args, manifest: Option<&Manifest>) -> Result<RunConfig> {
    let mut cfg = match (&args.config, manifest, &args.resume) {
        (Some(path), _, _) => rfcl_core::config::resolve_file(path, &args.overrides)
            .with_context(|| format!("loading the config {}", path.display()))?,
        (None, Some(m), Some(dir)) => {
            let path = checkpoint::checkpoint_dir(dir).join("config.yml");
            rfcl_core::atomic::atomic_write(&path, m.config_yaml.as_bytes())
                .with_context(|| format!("writing {}", path.display()))?;
            rfcl_core::config::resolve_file(&path, &args.overrides)
                .with_context(|| format!("loading the checkpoint's config {}", path.display()))?
        }
        _ => bail!("--config is required"),
    };
    if let Some(m) = manifest {
        if rfcl_core::config::to_yaml(&cfg) != m.config_yaml {
            tracing::warn!(
                "the config differs from the one the checkpoint was written under; resuming with the new one"
            );
        }
    }
    match args.device.as_deref() {
        Some("cpu") => cfg.sac.device = Device::Cpu,
        Some("cuda") => cfg.sac.device = Device::Cuda,
        _ => {}
    }
    Ok(cfg)
}

/// Demo selection (spec 6.1) and the dims check against `env.obs_dim` / `env.action_dim`.
fn load_demos(args: &Args, cfg: &RunConfig) -> Result<DemoSet> {
    let path = match (&args.demos, &cfg.train.dataset_path) {
        (Some(p), _) => p.clone(),
        (None, Some(p)) => PathBuf::from(p),
        (None, None) => bail!("no demos: pass --demos FILE or set train.dataset_path"),
    };
    rfcl_runtime::isolated::refuse_if_it_crashes(&path, "HDF5")?;
    let all = DemoSet::load(&path).with_context(|| format!("loading demos {}", path.display()))?;
    let demos = all
        .select(
            cfg.train.num_demos as usize,
            cfg.train.shuffle_demos,
            cfg.demo_seed.unwrap_or(cfg.seed),
        )
        .with_context(|| format!("selecting demos from {}", path.display()))?;
    demos.check_dims(
        cfg.env.obs_dim.map(|d| d as usize),
        cfg.env.action_dim.map(|d| d as usize),
    )?;
    tracing::info!(
        demos = demos.demos.len(),
        obs_dim = demos.obs_dim,
        action_dim = demos.action_dim,
        "demos from {}",
        path.display()
    );
    Ok(demos)
}
