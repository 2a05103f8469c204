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
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Parser;
use rfcl_core::config::{Device, RunConfig, StagePlan};
use rfcl_core::demo::DemoSet;
use rfcl_core::final_counters::{FinalCounters, LearnerCounts, FINAL_COUNTERS_FILE};
use rfcl_learner::checkpoint::{self, Manifest};
use rfcl_learner::service::{self, LearnerService, RunDescription};
use rfcl_learner::stages;
use rfcl_learner::trainer::{StopReason, Trainer, TrainerInputs};
use rfcl_proto::auth::{ClientAuth, ServerAuth};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, oneshot, watch};

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

    let listener = TcpListener::bind(SocketAddr::new(args.bind, args.port))
        .await
        .with_context(|| format!("binding the gRPC port {}:{}", args.bind, args.port))?;
    let addr = listener.local_addr().context("reading the bound address")?;
    let metrics_listener = match args.metrics_port {
        Some(port) => {
            let l = TcpListener::bind(SocketAddr::new(args.bind, port))
                .await
                .with_context(|| format!("binding the metrics port {}:{port}", args.bind))?;
            let at = l
                .local_addr()
                .context("reading the bound metrics address")?;
            Some((l, at))
        }
        None => None,
    };
    let layout = trainer.layout();
    let info = RunDescription {
        run_name: cfg.name.clone(),
        env_id: trainer.env_id().to_string(),
        obs_dim: layout.obs_dim as u32,
        action_dim: layout.action_dim as u32,
        curriculum_addr: args.curriculum.clone(),
        config_yaml: trainer.config_yaml().to_string(),
        run_seed: cfg.seed,
        learner_hostname: hostname(),
        run_id: rfcl_shm::new_run_id(),
        host_identity: rfcl_shm::host_identity(),
        shm: None,
        action_scale: trainer.action_scale().map(<[f32]>::to_vec),
    };
    let counters = rfcl_learner::ingest::IngestCounters::new();

    let (data_tx, data_rx) = mpsc::channel(args.queue_batches.max(1));
    let (stage_tx, stage_rx) = mpsc::unbounded_channel();
    let (shutdown_tx, shutdown_rx) = watch::channel(false);
    let (stopping_tx, stopping_rx) = watch::channel(false);
    // Same-host actors: transitions in and policies out over iceoryx2 (learner/src/shm.rs).
    let shm = (!args.no_shm)
        .then(|| {
            rfcl_learner::shm::ShmTransport::start_for(
                &info,
                layout,
                &status,
                &data_tx,
                &policy_rx,
                &counters,
                &stopping_rx,
            )
        })
        .transpose()
        .context("starting the shared-memory transport (--no-shm serves gRPC only)")?;
    let info = RunDescription {
        shm: shm.as_ref().map(|s| s.names.clone()),
        ..info
    };
    let service = LearnerService::new(
        info,
        status.clone(),
        data_tx,
        policy_rx,
        stopping_rx.clone(),
        counters.clone(),
        server_auth.guard.clone(),
    )
    .with_transition_batch(cfg.service.transition_batch);

    // Every task here serves until the stop: one that ends or fails earlier stops the learner
    // (after its final checkpoint) with an error naming it.
    let mut tasks = rfcl_runtime::tasks::Tasks::default();
    let metrics_url = match metrics_listener {
        Some((listener, at)) => {
            let mut stopped = stopping_rx.clone();
            let metrics = trainer.metrics();
            metrics.add_collector(counters.clone());
            metrics.add_collector(std::sync::Arc::new(rfcl_learner::prom::Unauthenticated(
                server_auth.guard.clone(),
            )));
            let serve = rfcl_learner::prom::serve(listener, metrics, async move {
                let _ = stopped.wait_for(|s| *s).await;
            });
            tasks.spawn("metrics server", async move {
                serve.await.context("serving /metrics")
            });
            let url = rfcl_learner::prom::describe(at);
            tracing::info!("Prometheus metrics at {url}");
            Some(url)
        }
        None => None,
    };
    // The one machine-readable line on stdout: `rfcl train` and tests read the address from it.
    let grpc = addr.to_string();
    let mut ready = vec![("grpc", grpc.as_str())];
    ready.extend(metrics_url.as_deref().map(|url| ("metrics", url)));
    println!("{}", rfcl_core::ready::ReadyLine::new("learner", &ready));

    // The first subscription was made before this learner could serve; subscribe again with its
    // address so that the curriculum server's dashboard polls its Health. The new stream's first
    // announcement goes to the trainer too, in case the stage moved in between.
    let advertise = args
        .advertise
        .clone()
        .unwrap_or_else(|| advertised_url(addr, server_auth.tls()));
    rfcl_proto::convert::learner_addr(&rfcl_proto::v1::WatchStageRequest {
        learner_addr: advertise.clone(),
    })
    .context("--advertise (RFCL_LEARNER_ADVERTISE)")?;
    let stage_stream = match stages::open(&args.curriculum, &client_auth, timeout, &advertise).await
    {
        Ok((announced, current)) => {
            drop(stage_stream);
            let _ = stage_tx.send(current);
            tracing::info!("announced to the curriculum server at {advertise}");
            announced
        }
        // Training does not need the panel: go on with the first subscription, which announces
        // this learner once it is re-opened.
        Err(e) => {
            tracing::warn!(
                "could not announce this learner at {advertise} to the curriculum server ({}); its dashboard shows no learner panel until the stage subscription is re-opened",
                rfcl_learner::error::chain(&e)
            );
            stage_stream
        }
    };
    let follow = stages::follow(
        args.curriculum.clone(),
        client_auth,
        advertise,
        stage_stream,
        stage_tx,
        stopping_rx.clone(),
    );
    let mut stopped = stopping_rx.clone();
    tasks.spawn("stage subscription", async move {
        follow.await;
        // It also ends when the training thread, its receiver, is done: wait for the stop then.
        let _ = stopped.wait_for(|s| *s).await;
        Ok(())
    });
    let inputs = TrainerInputs {
        data: data_rx,
        stages: stage_rx,
        shutdown: shutdown_rx,
        runtime: tokio::runtime::Handle::current(),
    };
    let (done_tx, mut done_rx) = oneshot::channel();
    std::thread::Builder::new()
        .name("trainer".into())
        .spawn(move || {
            let _ = done_tx.send(trainer.run(inputs, first_stage));
        })
        .context("starting the training thread")?;
    let mut stopped = stopping_rx.clone();
    let serve = service::serve(listener, service, server_auth, async move {
        let _ = stopped.wait_for(|s| *s).await;
    });
    tasks.spawn(
        "gRPC server",
        async move { serve.await.context("gRPC server") },
    );

    let mut failed = None;
    let outcome = tokio::select! {
        done = &mut done_rx => done,
        e = tasks.first_end() => {
            tracing::error!("{e:#}: finishing (final checkpoint)");
            failed = Some(e);
            let _ = shutdown_tx.send(true);
            (&mut done_rx).await
        }
        _ = signals.recv() => {
            tracing::info!("signal received: finishing (final checkpoint); signal again to abort");
            let _ = shutdown_tx.send(true);
            tokio::select! {
                done = &mut done_rx => done,
                _ = signals.recv() => bail!("aborted by a second signal before the final checkpoint"),
            }
        }
    };
    let _ = stopping_tx.send(true);
    if let Some(shm) = shm {
        let _ = tokio::task::spawn_blocking(move || shm.join(Duration::from_secs(5))).await;
    }
    let totals = counters.totals();
    tracing::info!("transitions taken in: {totals}");
    if matches!(outcome, Ok(Ok(_))) {
        let s = status.snapshot();
        let last = FinalCounters {
            pid: std::process::id(),
            counts: LearnerCounts {
                env_steps: s.env_steps,
                updates: s.critic_updates,
                policy_version: s.policy_version,
                shm_records: totals.shm_records,
                grpc_records: totals.grpc_records,
                shm_lost_records: totals.shm_lost_records,
                refused_batches: totals.refused_batches,
                dropped_stale_epoch: s.dropped_stale_epoch,
                unused_records: totals.unused_records,
            },
        };
        let path = run_dir.join(FINAL_COUNTERS_FILE);
        let json = serde_json::to_vec_pretty(&last).expect("counters serialize");
        if let Err(e) = rfcl_core::atomic::atomic_write(&path, &json) {
            tracing::warn!("writing {}: {e}", path.display());
        }
    }
    if let Err(e) = tasks.finish(Duration::from_secs(5)).await {
        tracing::warn!("stopping: {e:#}");
    }
    if let Some(e) = failed {
        return Err(e);
    }
    match outcome {
        Ok(Ok(reason)) => {
            let why = match reason {
                StopReason::Budget => "train.steps reached",
                StopReason::Signal => "stopped by a signal",
                StopReason::CurriculumFinished => "the curriculum server ended the run",
                StopReason::InputsClosed => "the ingest queue closed",
            };
            tracing::info!("learner done: {why}");
            Ok(())
        }
        Ok(Err(e)) => Err(e).context("training"),
        Err(_) => bail!("the training thread panicked"),
    }
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

/// The URL of this learner's gRPC as another host names it: the bound address, or this host's
/// name when bound to every interface.
fn advertised_url(bound: SocketAddr, tls: bool) -> String {
    let scheme = if tls { "https" } else { "http" };
    let host = match bound.ip() {
        ip if ip.is_unspecified() => hostname(),
        IpAddr::V6(ip) => format!("[{ip}]"),
        IpAddr::V4(ip) => ip.to_string(),
    };
    format!("{scheme}://{host}:{}", bound.port())
}

fn hostname() -> String {
    std::fs::read_to_string(Path::new("/proc/sys/kernel/hostname"))
        .map(|s| s.trim().to_string())
        .ok()
        .filter(|s| !s.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "localhost".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_advertised_url_is_the_bound_address_or_the_host_name() {
        let at = |ip: &str| SocketAddr::new(ip.parse().unwrap(), 50052);
        assert_eq!(
            advertised_url(at("127.0.0.1"), false),
            "http://127.0.0.1:50052"
        );
        assert_eq!(advertised_url(at("::1"), true), "https://[::1]:50052");
        assert_eq!(
            advertised_url(at("0.0.0.0"), false),
            format!("http://{}:50052", hostname())
        );
    }
}
