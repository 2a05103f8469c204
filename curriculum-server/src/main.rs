//! `curriculum-server`: the single writer of RFCL curriculum state (spec sections 2-4), serving
//! reset leases over gRPC and the curriculum dashboard over HTTP.
use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::Parser;
use rfcl_core::demo::DemoSet;
use rfcl_curriculum::server::{serve, Bound};
use rfcl_curriculum::service::Shared;
use rfcl_curriculum::state::{demo_metas, unix_now, DemoResets, ServerState};
use rfcl_curriculum::videos::VideoStore;
use rfcl_curriculum::{snapshot, Curriculum};
use rfcl_proto::auth::{ClientAuth, ServerAuth};

#[derive(Parser)]
#[command(
    name = "curriculum-server",
    version,
    about = "RFCL curriculum server: reset leases over gRPC, dashboard over HTTP"
)]
struct Args {
    /// gRPC port (0 = a free one; the chosen ports are printed on stdout).
    #[arg(long, default_value_t = 0)]
    port: u16,
    /// Dashboard HTTP port (0 = a free one).
    #[arg(long, default_value_t = 0)]
    dashboard_port: u16,
    /// Address to bind both ports on.
    #[arg(long, default_value = "127.0.0.1")]
    bind: IpAddr,
    /// Demo file (ManiSkill-format .h5 with its .json sidecar); default: the config's train.dataset_path.
    #[arg(long)]
    demos: Option<PathBuf>,
    /// Run config (YAML).
    #[arg(long)]
    config: PathBuf,
    /// Directory for snapshots; default runs/<name>. When it holds a snapshot, the server
    /// continues from it.
    #[arg(long, value_name = "RUN_DIR")]
    run_dir: Option<PathBuf>,
    /// Continue the curriculum from the snapshot in this run directory.
    #[arg(long, value_name = "RUN_DIR", conflicts_with = "run_dir")]
    resume: Option<PathBuf>,
    /// Dotted config overrides, e.g. `reverse.reverse_step_size=8`.
    overrides: Vec<String>,
}

fn main() -> ExitCode {
    // A damaged demo file can crash libhdf5: read once in a child copy of this binary first.
    rfcl_runtime::isolated::serve_if_child(|file| {
        DemoSet::load(file).map(drop).map_err(Into::into)
    });
    rfcl_runtime::init_logging();
    let args = Args::parse();
    rfcl_runtime::run(rfcl_runtime::Flavor::MultiThread, run(args))
}

async fn run(args: Args) -> Result<()> {
    // Every call needs the run's token (and TLS when configured): checked before anything else so
    // a missing token fails at once.
    let auth = ServerAuth::from_env().context("the curriculum server's gRPC service")?;
    let cfg = rfcl_core::config::resolve_file(&args.config, &args.overrides)?;
    let demo_path = match (&args.demos, &cfg.train.dataset_path) {
        (Some(p), _) => p.clone(),
        (None, Some(p)) => PathBuf::from(p),
        (None, None) => bail!(
            "no demos: pass --demos FILE or set train.dataset_path in {}",
            args.config.display()
        ),
    };
    rfcl_runtime::isolated::refuse_if_it_crashes(&demo_path, "HDF5")?;
    let all = DemoSet::load(&demo_path)?;
    let demos = all.select(
        cfg.train.num_demos as usize,
        cfg.train.shuffle_demos,
        cfg.demo_seed.unwrap_or(cfg.seed),
    )?;
    demos.check_dims(
        cfg.env.obs_dim.map(|d| d as usize),
        cfg.env.action_dim.map(|d| d as usize),
    )?;

    let run_dir = args
        .resume
        .clone()
        .or(args.run_dir.clone())
        .unwrap_or_else(|| PathBuf::from("runs").join(&cfg.name));
    std::fs::create_dir_all(&run_dir)
        .with_context(|| format!("creating the run directory {}", run_dir.display()))?;
    // Held until the process ends: a second curriculum-server on this directory is refused before it
    // writes anything.
    let _lock = rfcl_core::run_lock::RunDirLock::acquire(&run_dir, "curriculum-server")?;
    // A server that finds its own snapshot in its run directory continues it (a restarted
    // container, a supervisor's restart): the run goes on without anyone passing --resume.
    let newest = snapshot::load_newest(&run_dir, &cfg.name)?;
    if newest.is_none() && args.resume.is_some() {
        bail!(
            "--resume: {} holds no curriculum snapshot ({})",
            run_dir.display(),
            snapshot::SNAPSHOT_FILE
        );
    }
    let state = if let Some(loaded) = newest {
        if let Some(damage) = &loaded.skipped {
            tracing::warn!(
                "the newest snapshot is damaged ({}): resuming from the generation before it, {}; \
                 the reports since then are lost",
                rfcl_core::error::chain(damage),
                loaded.path.display()
            );
        }
        let mut state = loaded.state;
        let env_steps = state.stats.env_steps;
        let resumed = state
            .curriculum
            .resume_under(&cfg, &demo_metas(&demos), env_steps)
            .with_context(|| format!("resuming the run in {}", run_dir.display()))?;
        if !resumed.forward_adopted.is_empty() {
            tracing::info!(
                changes = %resumed.forward_adopted.join(", "),
                "stage 2 has not begun: its forward curriculum is rebuilt under the config's options"
            );
        }
        if !resumed.reverse_ignored.is_empty() {
            tracing::warn!(
                changes = %resumed.reverse_ignored.join(", "),
                "stage 1 has ended: changed reverse-curriculum options have no effect"
            );
        }
        if let Some(change) = &resumed.horizon_adopted {
            tracing::info!(
                change = %change,
                "stage 1 has ended: stage-2 episodes end at the config's horizon"
            );
        }
        if let Some(change) = resumed.stage_change {
            tracing::info!(
                from = ?change.from,
                to = ?change.to,
                epoch = change.epoch,
                env_steps,
                "the config the run resumes under changes its stage plan"
            );
        }
        tracing::info!(
            reports = state.stats.episodes,
            env_steps = state.stats.env_steps,
            "resumed the curriculum from the snapshot in {}",
            run_dir.display()
        );
        state
    } else {
        ServerState::new(Curriculum::new(&cfg, &demo_metas(&demos))?, unix_now())
    };
    tracing::info!(demos = demos.demos.len(), file = %demo_path.display(), "curriculum over {} demos", demos.demos.len());
    let shared = Shared::new(
        state,
        cfg,
        DemoResets::from_demos(&demos),
        auth.guard.clone(),
    )
    .with_learner_auth(
        ClientAuth::from_env().context("polling the learner's Health for the dashboard")?,
    )
    .with_videos(
        VideoStore::open(Some(run_dir.clone()))
            .with_context(|| format!("listing the eval videos in {}", run_dir.display()))?,
    );
    let bound = Bound::bind(
        SocketAddr::new(args.bind, args.port),
        SocketAddr::new(args.bind, args.dashboard_port),
    )
    .await?;
    let (grpc, dash) = bound.addrs()?;
    // One machine-readable line on stdout: `rfcl train` and tests read the ports from it.
    println!(
        "{}",
        rfcl_core::ready::ReadyLine::new(
            "curriculum-server",
            &[
                ("grpc", &grpc.to_string()),
                ("dashboard", &format!("http://{dash}/")),
            ],
        )
    );
    serve(
        shared,
        bound,
        auth,
        Some(run_dir),
        rfcl_runtime::shutdown_signal(),
    )
    .await
}
