//! `rfcl train`: one RFCL run on this machine (docs/DESIGN.md, "Processes").
//!
//! It resolves the config into `RUN_DIR/config.yml`, starts the curriculum server, the learner,
//! `service.num_actors` actors (`env.num_envs` split over them) and `service.num_eval_actors` eval
//! actors as child processes on 127.0.0.1 (binaries next to `rfcl`), and then watches them:
//!
//! * a progress bar (env steps / `train.steps`, stage, last eval success, updates/s, ETA) from the
//!   learner's Health and the curriculum's GetState;
//! * a dead actor is respawned, and said so; a dead curriculum server or learner (any signal, any
//!   exit status but the learner's 0) is restarted on its port from its last snapshot or
//!   checkpoint, after a backoff (1, 2, 4, ... s), and the log, `train_progress.json` and the
//!   summary say which process, why and what was rolled back; more than
//!   [`SERVICE_RESTARTS_MAX`] deaths of one service within [`SERVICE_RESTART_WINDOW_S`] stop the
//!   run with its error (the last lines of its log). The actors and the other service reconnect
//!   by themselves;
//! * the run ends when the learner exits after its budget, or when the mean success of the last 5
//!   evaluations reaches `service.stop_at_eval_success`; Ctrl-C / SIGTERM stops it cleanly, and
//!   `--resume RUN_DIR` continues it;
//! * at the end it writes and prints `RUN_DIR/summary.json` (also when a failure ends the run:
//!   `ending: failed` with the `error`).
//!
//! Files in the run directory beside the services' own: `config.yml` (resolved), `logs/<child>.log`,
//! `processes.json` (while a session runs: the services' addresses, every child's name and pid),
//! `train_progress.json` (wall time of earlier sessions, eval completion times), `summary.json`.
pub mod children;
pub mod progress;

use std::ffi::OsString;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rfcl_core::config::{resolve_file, to_yaml, RunConfig};
use rfcl_core::final_counters::{FinalCounters, LearnerCounts, FINAL_COUNTERS_FILE};
use rfcl_core::run_lock::RunDirLock;
use rfcl_core::run_state::RunState;
use rfcl_proto::auth::{self, AuthChannel, ClientAuth, Token};
use rfcl_proto::v1;
use rfcl_proto::v1::curriculum_client::CurriculumClient;
use rfcl_proto::v1::learner_client::LearnerClient;
use rfcl_runtime::Signals;
use tonic::transport::Channel;

use children::{describe, find_setpriv, Child, Launcher};
use progress::{
    restart_delay_s, split_envs, summarize, CompleteEval, CountersSource, Ending, EvalTracker,
    LearnerCounters, RespawnLimiter, RolledBack, RunProgress, RunShape, ServiceRestart, Silence,
    SilenceAction, Summary,
};

/// How long a service may take to print its ready line (the learner loads demos and may restore
/// a replay buffer from a checkpoint).
const READY_TIMEOUT: Duration = Duration::from_secs(180);
const POLL_EVERY: Duration = Duration::from_millis(500);
const STATE_EVERY: u32 = 4;
/// Ticks between saves of the session's wall time: a killed session loses at most 30 s of it.
const PROGRESS_EVERY: u32 = 60;
/// Grace periods between SIGTERM and SIGKILL.
const ACTOR_GRACE: Duration = Duration::from_secs(5);
const LEARNER_GRACE: Duration = Duration::from_secs(120);
const SERVER_GRACE: Duration = Duration::from_secs(20);
/// How long the end of a run waits for the next episode of the final policy's evaluation.
const FINAL_EVAL_PATIENCE: Duration = Duration::from_secs(60);
/// A service silent this long is said to be so (it is killed at `service.hang_timeout_s`).
const SILENCE_WARN_S: f64 = 15.0;
/// A service that dies more often than this within the window cannot run: the run stops.
pub const SERVICE_RESTARTS_MAX: usize = 3;
pub const SERVICE_RESTART_WINDOW_S: f64 = 600.0;

/// What `rfcl train` was asked to do.
#[derive(Debug, Clone)]
pub struct TrainArgs {
    /// The run config; `None` only with `resume` (the run's stored config is used).
    pub config: Option<PathBuf>,
    pub overrides: Vec<String>,
    pub resume: Option<PathBuf>,
    pub run_dir: Option<PathBuf>,
    /// `learner --threads`; `None`: `learner.threads` of the config (default all cores but one).
    pub learner_threads: Option<u32>,
}

/// Runs a training session to its end. Runs on the calling (main) thread: children are forked from
/// it, which their parent-death signal depends on.
pub fn train(args: TrainArgs) -> Result<Summary> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(train_async(args))
}

/// The resolved run: config, directory, demos.
#[derive(Debug)]
struct Prepared {
    cfg: RunConfig,
    learner_threads: u32,
    run_dir: PathBuf,
    config_path: PathBuf,
    demos: PathBuf,
    resume: bool,
    progress: RunProgress,
    /// This launcher owns the run directory until it ends (a second `rfcl train` on it is refused).
    _lock: RunDirLock,
}

fn prepare(args: &TrainArgs) -> Result<Prepared> {
    let (cfg, run_dir, resume) = match &args.resume {
        Some(dir) => {
            let stored = dir.join("config.yml");
            if !stored.is_file() {
                bail!(
                    "{} is not a run directory to resume: it has no config.yml",
                    dir.display()
                );
            }
            let cfg = resolve_file(&stored, &args.overrides)
                .with_context(|| format!("the stored config of the run in {}", dir.display()))?;
            if let Some(path) = &args.config {
                let mut requested = resolve_file(path, &args.overrides)?;
                if requested.train.dataset_path.is_none() {
                    requested.train.dataset_path = cfg.train.dataset_path.clone();
                }
                if requested != cfg {
                    eprintln!(
                        "note: resuming with the run's stored config ({}) and the overrides \
                         given; it differs from {}",
                        stored.display(),
                        path.display()
                    );
                }
            }
            (cfg, dir.clone(), true)
        }
        None => {
            let Some(path) = &args.config else {
                bail!(
                    "a run config is needed: `rfcl train CONFIG`, or `rfcl train --resume RUN_DIR`"
                );
            };
            let requested = resolve_file(path, &args.overrides)?;
            let run_dir = match &args.run_dir {
                Some(dir) => dir.clone(),
                None => free_run_dir(&PathBuf::from("runs"), &requested.name),
            };
            (requested, run_dir, false)
        }
    };
    let mut cfg = cfg;
    if let Some(threads) = args.learner_threads {
        if threads == 0 {
            bail!("--learner-threads must be at least 1, got 0");
        }
        // Stored in the run's config.yml, so that `--resume` keeps the thread count the run was
        // started with.
        cfg.learner.threads = Some(threads);
    }
    check_runnable(&cfg)?;
    let demos = PathBuf::from(cfg.train.dataset_path.clone().expect("checked"));
    std::fs::create_dir_all(run_dir.join("logs"))
        .with_context(|| format!("creating the run directory {}", run_dir.display()))?;
    // Before anything is written: a second launcher on this directory stops here.
    let lock = RunDirLock::acquire(&run_dir, "rfcl")?;
    if let Some(short) = children::short_of_space(&run_dir) {
        bail!(
            "{short}: a run writes its checkpoints (the replay buffer with them), snapshots and logs \
             there; free space or choose another --run-dir"
        );
    }
    if !resume && run_dir.join("config.yml").exists() {
        bail!(
            "{} already holds a run: continue it with --resume {} or choose another --run-dir",
            run_dir.display(),
            run_dir.display()
        );
    }
    let config_path = run_dir.join("config.yml");
    rfcl_core::atomic::atomic_write(&config_path, to_yaml(&cfg).as_bytes())
        .with_context(|| format!("writing {}", config_path.display()))?;
    let mut progress = if resume {
        read_progress(&run_dir)?
    } else {
        RunProgress::default()
    };
    progress.begin_session();
    // At least 1: the flag is checked above, `learner.threads` by the config's validation.
    let learner_threads = cfg.learner.threads_here(None);
    Ok(Prepared {
        cfg,
        learner_threads,
        run_dir,
        config_path,
        demos,
        resume,
        progress,
        _lock: lock,
    })
}

/// `runs/<name>`, or `runs/<name>-2`, `-3`, ... when it already holds a run.
fn free_run_dir(root: &Path, name: &str) -> PathBuf {
    let first = root.join(name);
    if !first.join("config.yml").exists() {
        return first;
    }
    (2..)
        .map(|n| root.join(format!("{name}-{n}")))
        .find(|d| !d.join("config.yml").exists())
        .expect("an unbounded range has a free name")
}

/// What must hold before any process starts.
fn check_runnable(cfg: &RunConfig) -> Result<()> {
    let Some(demos) = &cfg.train.dataset_path else {
        bail!(
            "train.dataset_path is not set: `rfcl train` generates nothing by itself. Make demos, \
             e.g. `rfcl demos generate --env pointmaze -n 5 --out runs/demos/pointmaze.h5`, and \
             pass train.dataset_path=runs/demos/pointmaze.h5"
        );
    };
    if !Path::new(demos).is_file() {
        bail!("train.dataset_path: demo file {demos} not found");
    }
    crate::demos::check::refuse_if_it_crashes_the_reader(Path::new(demos))
        .context("train.dataset_path")?;
    rfcl_actor::suite::check_supported(&cfg.env)?;
    // The reader does not crash on the file (checked just above); the services read it again.
    let set = rfcl_core::demo::DemoSet::load(Path::new(demos))
        .with_context(|| format!("train.dataset_path: reading {demos}"))?;
    rfcl_actor::suite::check_demos_fit(&cfg.env, &set)
        .with_context(|| format!("train.dataset_path {demos}"))?;
    let s = &cfg.service;
    if s.num_actors == 0 {
        bail!("service.num_actors must be at least 1");
    }
    if cfg.env.num_envs < s.num_actors {
        bail!(
            "env.num_envs ({}) must be at least service.num_actors ({}): every actor steps at \
             least one env",
            cfg.env.num_envs,
            s.num_actors
        );
    }
    if s.num_eval_actors > 0 && cfg.eval_env.num_envs < s.num_eval_actors {
        bail!(
            "eval_env.num_envs ({}) must be at least service.num_eval_actors ({})",
            cfg.eval_env.num_envs,
            s.num_eval_actors
        );
    }
    if s.num_eval_actors == 0 && s.stop_at_eval_success.is_some() {
        eprintln!(
            "note: service.stop_at_eval_success is set but service.num_eval_actors is 0: \
             the run uses its whole budget"
        );
    }
    Ok(())
}

const PROGRESS_FILE: &str = "train_progress.json";

fn read_progress(run_dir: &Path) -> Result<RunProgress> {
    let path = run_dir.join(PROGRESS_FILE);
    match std::fs::read_to_string(&path) {
        Ok(text) => {
            serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(RunProgress::default()),
        Err(e) => Err(e).with_context(|| format!("reading {}", path.display())),
    }
}

fn write_json(path: &Path, value: &impl serde::Serialize) -> Result<()> {
    let text = serde_json::to_string_pretty(value)?;
    rfcl_core::atomic::atomic_write(path, format!("{text}\n").as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

/// An actor process and how to restart it.
struct ActorProc {
    id: u32,
    eval: bool,
    envs: u32,
    child: Option<Child>,
    /// Exited by itself with success (the curriculum finished): not respawned.
    done: bool,
}

/// The two services `rfcl train` restarts when they die.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Service {
    Curriculum,
    Learner,
}

impl Service {
    /// The child's name, which is also its binary's.
    fn name(self) -> &'static str {
        match self {
            Service::Curriculum => "curriculum-server",
            Service::Learner => "learner",
        }
    }

    fn id(self) -> u32 {
        self as u32
    }

    /// What it restarts from.
    fn saved_state(self) -> &'static str {
        match self {
            Service::Curriculum => "snapshot",
            Service::Learner => "checkpoint",
        }
    }
}

/// The processes of a running session and what is known of them.
struct Session {
    prep: Prepared,
    launcher: Launcher,
    server: Child,
    learner: Option<Child>,
    /// How each service is started again: on the port it had, from the run directory (which
    /// holds its snapshot or checkpoint).
    server_args: Vec<OsString>,
    learner_args: Vec<OsString>,
    service_deaths: RespawnLimiter,
    learner_addr: String,
    curriculum_addr: String,
    dashboard: String,
    actors: Vec<ActorProc>,
    curriculum: CurriculumClient<AuthChannel>,
    learner_client: LearnerClient<AuthChannel>,
    started: Instant,
    evals: EvalTracker,
    counters: LearnerCounters,
    last_view: Option<RunState>,
    respawns: RespawnLimiter,
    bar: Bar,
    updates_per_s: f64,
    last_health: Option<(Instant, u64)>,
    /// The pid of a learner that ended the run by exiting by itself.
    learner_exited: Option<u32>,
    /// How long each service has not answered, and the one killed for it (the cause of its
    /// restart).
    server_silence: Silence,
    learner_silence: Silence,
    killed_silent: Option<(Service, f64)>,
}

async fn train_async(args: TrainArgs) -> Result<Summary> {
    let prep = prepare(&args)?;
    let bin_dir = std::env::current_exe()
        .context("locating the rfcl executable")?
        .parent()
        .map(Path::to_path_buf)
        .context("the rfcl executable has no directory")?;
    let setpriv = find_setpriv();
    if setpriv.is_none() {
        eprintln!(
            "warning: setpriv (util-linux) not found: if rfcl is killed with SIGKILL its children \
             keep running"
        );
    }
    let launcher = Launcher {
        bin_dir,
        log_dir: prep.run_dir.join("logs"),
        setpriv,
        token: run_token(&prep.run_dir)?,
    };
    eprintln!(
        "{} run '{}' in {} (logs in {})",
        if prep.resume { "resuming" } else { "starting" },
        prep.cfg.name,
        prep.run_dir.display(),
        launcher.log_dir.display()
    );
    // Ctrl-C and SIGTERM, installed before the first child starts, so an interrupt at any moment
    // (a service still starting included) stops the children rather than leaving them behind.
    let mut signals = Signals::install()?;
    // Dropping a half-started session kills the children it started (`kill_on_drop`).
    let mut session = tokio::select! {
        session = Session::start(prep, launcher) => session?,
        _ = signals.recv() => bail!(
            "interrupted while the services were starting: stopped them; nothing was trained in \
             this session"
        ),
    };
    let ending = session.supervise(&mut signals).await;
    session.finish(ending).await
}

/// The token every call between this run's processes carries: the one in the environment
/// (`RFCL_TOKEN` or `RFCL_TOKEN_FILE`) when set, else a fresh random one for this session. It is
/// written to `RUN_DIR/token` (owner-only), so actors started by hand on other hosts can join
/// (`RFCL_TOKEN_FILE=RUN_DIR/token actor --connect ...`).
fn run_token(run_dir: &Path) -> Result<Token> {
    let token = if std::env::var_os(auth::TOKEN_ENV).is_some()
        || std::env::var_os(auth::TOKEN_FILE_ENV).is_some()
    {
        Token::from_env().context("the run token given in the environment")?
    } else {
        Token::random()
    };
    let path = run_dir.join("token");
    {
        use std::io::Write;
        use std::os::unix::fs::OpenOptionsExt;
        let _ = std::fs::remove_file(&path);
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .open(&path)
            .with_context(|| format!("writing the run token to {}", path.display()))?;
        writeln!(file, "{}", token.expose())
            .with_context(|| format!("writing the run token to {}", path.display()))?;
    }
    Ok(token)
}

fn os(args: &[&str]) -> Vec<OsString> {
    args.iter().map(OsString::from).collect()
}

impl Session {
    async fn start(prep: Prepared, launcher: Launcher) -> Result<Session> {
        let cfg = &prep.cfg;
        let run_dir = prep.run_dir.as_os_str().to_owned();
        let config = prep.config_path.as_os_str().to_owned();
        let demos = prep.demos.as_os_str().to_owned();

        // Curriculum server.
        let server_args = |port: &str, dashboard_port: &str, resume: bool| {
            let mut args = vec![
                "--config".into(),
                config.clone(),
                "--demos".into(),
                demos.clone(),
            ];
            args.extend(os(&["--port", port, "--dashboard-port", dashboard_port]));
            args.push(if resume { "--resume" } else { "--run-dir" }.into());
            args.push(run_dir.clone());
            args
        };
        let mut server = launcher.spawn(
            "curriculum-server",
            "curriculum-server",
            server_args(
                &cfg.service.curriculum_port.to_string(),
                &cfg.service.dashboard_port.to_string(),
                prep.resume,
            ),
        )?;
        let line = server.ready_line(READY_TIMEOUT).await?;
        let (Some(curriculum_addr), Some(dashboard)) =
            (line.field("grpc"), line.field("dashboard"))
        else {
            bail!("unexpected ready line from the curriculum server: {line}");
        };
        let (curriculum_addr, dashboard) = (curriculum_addr.to_owned(), dashboard.to_owned());
        let curriculum_url = format!("http://{curriculum_addr}");
        // A restarted server resumes from the run directory's snapshot on the same ports, where
        // the learner and the actors look for it.
        let server_args = server_args(
            &port_of(&curriculum_addr)?.to_string(),
            &port_of(&dashboard)?.to_string(),
            false,
        );

        // Learner.
        let learner_args = |port: &str, resume: bool| {
            let mut args = vec![
                "--config".into(),
                config.clone(),
                "--demos".into(),
                demos.clone(),
            ];
            args.extend(os(&[
                "--curriculum",
                &curriculum_url,
                "--port",
                port,
                "--threads",
                &prep.learner_threads.to_string(),
                // Prometheus /metrics on a free port (its URL is on the ready line).
                "--metrics-port",
                "0",
            ]));
            args.push(if resume { "--resume" } else { "--run-dir" }.into());
            args.push(run_dir.clone());
            args
        };
        let mut learner = launcher.spawn(
            "learner",
            "learner",
            learner_args(&cfg.service.learner_port.to_string(), prep.resume),
        )?;
        let line = learner.ready_line(READY_TIMEOUT).await?;
        let Some(learner_addr) = line.field("grpc").map(str::to_owned) else {
            bail!("unexpected ready line from the learner: {line}");
        };
        let learner_args = learner_args(&port_of(&learner_addr)?.to_string(), false);
        let learner_url = format!("http://{learner_addr}");
        println!("dashboard: {dashboard}");
        eprintln!("curriculum server at {curriculum_url}, learner at {learner_url}");
        if let Some(metrics) = line.field("metrics") {
            eprintln!("learner metrics (Prometheus): {metrics}");
        }

        let client_auth = ClientAuth::plain(launcher.token.clone());
        let curriculum = CurriculumClient::new(client_auth.wrap(channel(&curriculum_url)?))
            .max_decoding_message_size(64 << 20);
        let learner_client = LearnerClient::new(client_auth.wrap(channel(&learner_url)?));

        // Actors: ids 0.. for training, then the eval actors.
        let s = &cfg.service;
        let mut actors = Vec::new();
        for (i, envs) in split_envs(cfg.env.num_envs, s.num_actors)
            .into_iter()
            .enumerate()
        {
            actors.push((i as u32, false, envs));
        }
        if s.num_eval_actors > 0 {
            for (j, envs) in split_envs(cfg.eval_env.num_envs, s.num_eval_actors)
                .into_iter()
                .enumerate()
            {
                actors.push((s.num_actors + j as u32, true, envs));
            }
        }
        let episodes_needed = rfcl_actor::eval::episodes_per_eval(cfg);
        let evals = EvalTracker::new(episodes_needed, &prep.progress.evals);
        let bar = Bar::new(cfg.train.steps);
        let mut session = Session {
            launcher,
            server,
            learner: Some(learner),
            server_args,
            learner_args,
            service_deaths: RespawnLimiter::new(SERVICE_RESTARTS_MAX, SERVICE_RESTART_WINDOW_S),
            learner_addr: learner_url,
            curriculum_addr: curriculum_url,
            dashboard,
            actors: actors
                .into_iter()
                .map(|(id, eval, envs)| ActorProc {
                    id,
                    eval,
                    envs,
                    child: None,
                    done: false,
                })
                .collect(),
            curriculum,
            learner_client,
            started: Instant::now(),
            evals,
            counters: LearnerCounters::default(),
            last_view: None,
            respawns: RespawnLimiter::new(5, 120.0),
            bar,
            updates_per_s: 0.0,
            last_health: None,
            learner_exited: None,
            server_silence: Silence::default(),
            learner_silence: Silence::default(),
            killed_silent: None,
            prep,
        };
        for i in 0..session.actors.len() {
            session.spawn_actor(i)?;
        }
        session.write_processes()?;
        Ok(session)
    }

    fn spawn_actor(&mut self, index: usize) -> Result<()> {
        let a = &self.actors[index];
        let name = if a.eval {
            format!("eval-actor-{}", a.id)
        } else {
            format!("actor-{}", a.id)
        };
        let mut args = os(&[
            "--connect",
            &self.learner_addr,
            "--envs",
            &a.envs.to_string(),
            "--id",
            &a.id.to_string(),
        ]);
        if a.eval {
            args.push("--eval".into());
        }
        let child = self.launcher.spawn(&name, "actor", args)?;
        self.actors[index].child = Some(child);
        Ok(())
    }

    fn wall_s(&self) -> f64 {
        self.prep.progress.earlier_sessions_s + self.started.elapsed().as_secs_f64()
    }

    /// `RUN_DIR/processes.json`: the services' addresses and every running child's name and pid
    /// (removed when the session ends).
    fn write_processes(&self) -> Result<()> {
        let mut list = vec![serde_json::json!({"name": self.server.name, "pid": self.server.pid})];
        if let Some(l) = &self.learner {
            list.push(serde_json::json!({"name": l.name, "pid": l.pid}));
        }
        for a in &self.actors {
            if let Some(c) = &a.child {
                list.push(serde_json::json!({"name": c.name, "pid": c.pid, "actor_id": a.id, "eval": a.eval}));
            }
        }
        let doc = serde_json::json!({
            "rfcl_pid": std::process::id(),
            "curriculum": self.curriculum_addr,
            "dashboard": self.dashboard,
            "learner": self.learner_addr,
            // The run's token lives in this file, never in processes.json itself.
            "token_file": self.prep.run_dir.join("token"),
            "children": list,
        });
        write_json(&self.prep.run_dir.join("processes.json"), &doc)
    }

    /// Watches the children and the run's progress until the run ends, fails or is interrupted.
    async fn supervise(&mut self, signals: &mut Signals) -> Result<Ending> {
        let mut tick = tokio::time::interval(POLL_EVERY);
        let mut ticks = 0u32;
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                _ = signals.recv() => return Ok(Ending::Interrupted),
            }
            ticks += 1;
            if let Some(status) = self.server.try_wait() {
                if let Some(ending) = self.restart(Service::Curriculum, status, signals).await? {
                    return Ok(ending);
                }
            }
            if let Some(learner) = self.learner.as_mut() {
                if let Some(status) = learner.try_wait() {
                    if status.success() {
                        self.learner_exited = Some(learner.pid);
                        self.learner = None;
                        if self.ended_by_itself().await == Ending::Budget
                            && !self.await_final_eval(signals).await
                        {
                            return Ok(Ending::Interrupted);
                        }
                        return Ok(self.ended_by_itself().await);
                    }
                    if let Some(ending) = self.restart(Service::Learner, status, signals).await? {
                        return Ok(ending);
                    }
                }
            }
            self.check_actors()?;
            let answered = self.poll_health().await;
            self.watch(Service::Learner, answered);
            if ticks % STATE_EVERY == 1 {
                let answered = self.poll_state().await;
                self.watch(Service::Curriculum, answered);
                if self
                    .evals
                    .reached(self.prep.cfg.service.stop_at_eval_success)
                {
                    return Ok(Ending::EvalSuccess);
                }
            }
            if ticks.is_multiple_of(PROGRESS_EVERY) {
                if let Err(e) = self.save_progress(false) {
                    self.bar.println(format!("warning: {e:#}"));
                }
            }
            self.draw();
            if self.actors.iter().filter(|a| !a.eval).all(|a| a.done) {
                self.bar
                    .println("every actor finished: the curriculum hands out no more leases");
                return Ok(self.ended_by_itself().await);
            }
        }
    }

    /// Restarts `service`, which died with `status`, from its last snapshot or checkpoint: after
    /// a backoff, on the port it had, until it is ready again or has died too often (an error).
    /// Records the restart with what it rolled back. `Some(Interrupted)` when Ctrl-C came first.
    async fn restart(
        &mut self,
        service: Service,
        status: std::process::ExitStatus,
        signals: &mut Signals,
    ) -> Result<Option<Ending>> {
        let name = service.name();
        let died_at = self.wall_s();
        let first_cause = match self.killed_silent.take_if(|(killed, _)| *killed == service) {
            Some((_, s)) => format!("killed after not answering for {s:.0} s"),
            None => describe(Some(status)),
        };
        let mut cause = first_cause.clone();
        let mut tail = match service {
            Service::Curriculum => self.server.log_tail(),
            Service::Learner => self
                .learner
                .as_ref()
                .map(Child::log_tail)
                .unwrap_or_default(),
        };
        // A full disk kills every restart the same way: say so instead of retrying.
        if let Some(short) = children::short_of_space(&self.prep.run_dir) {
            bail!(
                "the {name} died ({cause}) with {short}: its checkpoints and logs cannot be \
                 written there. Free space, then continue with `rfcl train --resume {}`{tail}",
                self.prep.run_dir.display()
            );
        }
        let before = self.rollback_counters();
        let (child, line) = loop {
            let now = self.wall_s();
            let recent = self.service_deaths.recent(service.id(), now);
            if !self.service_deaths.allow(service.id(), now) {
                bail!(
                    "the {name} died {} times within {SERVICE_RESTART_WINDOW_S} s (last: {cause}); \
                     stopping the run{tail}",
                    recent + 1
                );
            }
            let delay = restart_delay_s(recent);
            self.bar.println(format!(
                "the {name} died ({cause}); restarting it in {delay} s from its last {}{tail}",
                service.saved_state()
            ));
            tokio::select! {
                _ = tokio::time::sleep(Duration::from_secs(delay)) => {}
                _ = signals.recv() => return Ok(Some(Ending::Interrupted)),
            }
            let args = match service {
                Service::Curriculum => self.server_args.clone(),
                Service::Learner => self.learner_args.clone(),
            };
            let mut child = self.launcher.spawn(name, name, args)?;
            let ready = tokio::select! {
                ready = child.ready_line(READY_TIMEOUT) => ready,
                _ = signals.recv() => {
                    child.stop(LEARNER_GRACE).await;
                    return Ok(Some(Ending::Interrupted));
                }
            };
            match ready {
                Ok(line) => break (child, line),
                Err(e) => {
                    cause = format!("it failed to start again: {e:#}");
                    tail = String::new();
                }
            }
        };
        let pid = child.pid;
        match service {
            Service::Curriculum => {
                self.server = child;
                if let Some(view) = self.fetch_state().await {
                    self.take_view(view);
                }
            }
            Service::Learner => {
                self.learner = Some(child);
                self.last_health = None;
                for _ in 0..10 {
                    if self.poll_health().await {
                        break;
                    }
                    tokio::time::sleep(POLL_EVERY).await;
                }
                if let Some(metrics) = line.field("metrics") {
                    self.bar
                        .println(format!("learner metrics (Prometheus): {metrics}"));
                }
            }
        }
        let rolled_back = RolledBack::between(before, self.rollback_counters());
        self.bar.println(format!(
            "the {name} is back (pid {pid}) from its last {}: rolled back {} env steps, {} \
             updates, {} episode reports",
            service.saved_state(),
            rolled_back.env_steps,
            rolled_back.updates,
            rolled_back.reports
        ));
        self.prep.progress.restarts.push(ServiceRestart {
            process: name.to_owned(),
            wall_s: died_at,
            cause: first_cause,
            rolled_back,
        });
        self.write_processes()?;
        if let Err(e) = self.save_progress(false) {
            self.bar.println(format!("warning: {e:#}"));
        }
        Ok(None)
    }

    /// The counters a restart can roll back: the learner's env steps and updates (its last
    /// Health), the curriculum's episode reports (its last state).
    fn rollback_counters(&self) -> [u64; 3] {
        [
            self.counters.counts.env_steps,
            self.counters.counts.updates,
            self.last_view.as_ref().map_or(0, |v| v.episodes),
        ]
    }

    /// Why a run that ended by itself ended: the curriculum server's stop rule (the evals reached
    /// `service.stop_at_eval_success`), the end of stage 1 under `train.stage_1_only`, or the
    /// budget.
    async fn ended_by_itself(&mut self) -> Ending {
        self.poll_state().await;
        let stage_1_ended = self
            .last_view
            .as_ref()
            .is_some_and(|v| v.stage_1_env_steps.is_some());
        if self
            .evals
            .reached(self.prep.cfg.service.stop_at_eval_success)
        {
            Ending::EvalSuccess
        } else if self.prep.cfg.train.stage_1_only && stage_1_ended {
            Ending::Stage1Done
        } else {
            Ending::Budget
        }
    }

    /// A run that used its budget ends with the evaluation of its final policy when that policy
    /// passed an eval point not yet evaluated (the learner trains it on every env step of the
    /// budget, docs/LEARNER.md): the train actors stop, and the run waits while eval episodes come
    /// in, giving up after [`FINAL_EVAL_PATIENCE`] without one. False when Ctrl-C came first.
    async fn await_final_eval(&mut self, signals: &mut Signals) -> bool {
        let cfg = &self.prep.cfg;
        let Some(last) = self
            .learner_exited
            .and_then(|pid| read_final_counters(&self.prep.run_dir, pid))
        else {
            return true;
        };
        let final_policy = last.counts.policy_version;
        if cfg.service.num_eval_actors == 0
            || !self.evals.final_eval_pending(
                last.counts.env_steps,
                cfg.sac.eval_freq,
                cfg.sac.num_seed_steps,
            )
        {
            return true;
        }
        for actor in self.actors.iter_mut().filter(|a| !a.eval) {
            if let Some(child) = actor.child.as_mut() {
                child.stop(ACTOR_GRACE).await;
            }
        }
        self.bar.println(format!(
            "train.steps used: waiting for the evaluation of the final policy (version \
             {final_policy}, {} env steps)",
            last.counts.env_steps
        ));
        let episodes_reported = |view: &Option<RunState>| {
            view.as_ref()
                .map_or(0, |v| v.evals.iter().map(|p| p.episodes).sum::<u64>())
        };
        let mut reported = episodes_reported(&self.last_view);
        let mut last_news = Instant::now();
        let mut tick = tokio::time::interval(POLL_EVERY);
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                _ = signals.recv() => return false,
            }
            self.poll_state().await;
            if self
                .evals
                .evals()
                .iter()
                .any(|e| e.policy_version >= final_policy)
            {
                return true;
            }
            let now_reported = episodes_reported(&self.last_view);
            if now_reported > reported {
                (reported, last_news) = (now_reported, Instant::now());
            }
            let eval_actors_running = self
                .actors
                .iter_mut()
                .filter(|a| a.eval)
                .any(|a| a.child.as_mut().is_some_and(|c| c.try_wait().is_none()));
            let why = if !eval_actors_running {
                "the eval actors stopped".to_string()
            } else if last_news.elapsed() >= FINAL_EVAL_PATIENCE {
                format!(
                    "no evaluation episode came in for {} s",
                    FINAL_EVAL_PATIENCE.as_secs()
                )
            } else {
                self.draw();
                continue;
            };
            self.bar.println(format!(
                "warning: {why}: the run ends without the evaluation of its final policy"
            ));
            return true;
        }
    }

    fn check_actors(&mut self) -> Result<()> {
        let now = self.wall_s();
        let mut changed = false;
        for i in 0..self.actors.len() {
            let Some(child) = self.actors[i].child.as_mut() else {
                continue;
            };
            let Some(status) = child.try_wait() else {
                continue;
            };
            let name = child.name.clone();
            let tail = child.log_tail();
            self.actors[i].child = None;
            changed = true;
            if status.success() {
                self.bar.println(format!("{name} finished (exit status 0)"));
                self.actors[i].done = true;
                continue;
            }
            if !self.respawns.allow(self.actors[i].id, now) {
                bail!(
                    "{name} keeps dying ({}); stopping the run{tail}",
                    describe(Some(status))
                );
            }
            self.spawn_actor(i)?;
            self.prep.progress.actor_respawns += 1;
            let pid = self.actors[i].child.as_ref().map_or(0, |c| c.pid);
            self.bar.println(format!(
                "{name} died ({}); respawned it (pid {pid}){tail}",
                describe(Some(status))
            ));
        }
        if changed {
            self.write_processes()?;
        }
        Ok(())
    }

    /// Takes the learner's counters from its Health; false when it did not answer.
    async fn poll_health(&mut self) -> bool {
        let mut client = self.learner_client.clone();
        let Ok(Ok(reply)) =
            tokio::time::timeout(Duration::from_secs(2), client.health(v1::HealthRequest {})).await
        else {
            return false;
        };
        let h = reply.into_inner();
        let now = Instant::now();
        if let Some((t, updates)) = self.last_health {
            let dt = now.duration_since(t).as_secs_f64();
            if dt > 0.0 && h.updates >= updates {
                let rate = (h.updates - updates) as f64 / dt;
                self.updates_per_s = 0.8 * self.updates_per_s + 0.2 * rate;
            }
        }
        self.last_health = Some((now, h.updates));
        self.counters = LearnerCounters {
            source: CountersSource::LastPoll,
            counts: LearnerCounts {
                env_steps: h.env_steps,
                updates: h.updates,
                policy_version: h.policy_version,
                shm_records: h.shm_records,
                grpc_records: h.grpc_records,
                shm_lost_records: h.shm_lost_records,
                refused_batches: h.refused_batches,
                dropped_stale_epoch: h.dropped_stale_epoch,
                unused_records: h.unused_records,
            },
        };
        true
    }

    async fn fetch_state(&mut self) -> Option<RunState> {
        fetch_run_state(&mut self.curriculum.clone()).await
    }

    /// True when the curriculum server answered.
    async fn poll_state(&mut self) -> bool {
        let Some(view) = self.fetch_state().await else {
            return false;
        };
        if self.take_view(view) {
            if let Err(e) = self.save_progress(false) {
                self.bar.println(format!("warning: {e:#}"));
            }
        }
        true
    }

    /// Keeps count of a service's unanswered calls: says so once it has been silent a while, and
    /// kills it at `service.hang_timeout_s`, so that the supervisor restarts it as a dead one.
    fn watch(&mut self, service: Service, answered: bool) {
        let now = self.wall_s();
        let timeout = self.prep.cfg.service.hang_timeout_s;
        let (silence, child) = match service {
            Service::Curriculum => (&mut self.server_silence, Some(&self.server)),
            Service::Learner => (&mut self.learner_silence, self.learner.as_ref()),
        };
        let Some(child) = child else { return };
        if answered {
            silence.answered();
            return;
        }
        let (name, pid) = (service.name(), child.pid);
        match silence.silent(now, SILENCE_WARN_S, timeout) {
            SilenceAction::Wait => {}
            SilenceAction::Warn(s) => self.bar.println(match timeout {
                Some(t) => format!(
                    "the {name} (pid {pid}) has not answered for {s:.0} s; it is restarted if it \
                     stays silent for {t:.0} s (service.hang_timeout_s)"
                ),
                None => format!("the {name} (pid {pid}) has not answered for {s:.0} s"),
            }),
            SilenceAction::Kill(s) => {
                self.bar.println(format!(
                    "the {name} (pid {pid}) has not answered for {s:.0} s: killing it to restart it"
                ));
                child.signal(rustix::process::Signal::KILL);
                self.killed_silent = Some((service, s));
            }
        }
    }

    /// Keeps the curriculum server's latest state and prints and records the evals it completes;
    /// true if there were any.
    fn take_view(&mut self, view: RunState) -> bool {
        let fresh = self.evals.update(&view.evals, self.wall_s());
        let any = !fresh.is_empty();
        for eval in fresh {
            self.bar.println(format_eval(&eval));
            self.prep.progress.evals.push(eval);
        }
        self.last_view = Some(view);
        any
    }

    /// `RUN_DIR/train_progress.json`, with this session's wall time so far (`ended` = false) or
    /// folded into the earlier sessions' (`ended` = true).
    fn save_progress(&self, ended: bool) -> Result<()> {
        let session_s = self.started.elapsed().as_secs_f64();
        let p = if ended {
            self.prep.progress.after_session(session_s)
        } else {
            self.prep.progress.during_session(session_s)
        };
        write_json(&self.prep.run_dir.join(PROGRESS_FILE), &p)
    }

    fn draw(&self) {
        let stage = self.last_view.as_ref().map_or(1, |v| v.stage);
        let eval = self.evals.last().map_or("-".to_string(), |e| {
            format!("{:.0}%", 100.0 * e.success_at_end)
        });
        self.bar.update(
            self.counters.counts.env_steps,
            format!(
                "stage {stage} | eval {eval} | {:.1} upd/s",
                self.updates_per_s
            ),
        );
    }

    /// Stops every child in order (actors, learner, curriculum server) after taking the
    /// curriculum's final state, then writes the summary. The learner's counters are its own
    /// final ones, all from one moment, so they agree with each other.
    async fn finish(mut self, ending: Result<Ending>) -> Result<Summary> {
        if let Some(view) = self.fetch_state().await {
            self.take_view(view);
        }
        self.bar.finish();
        for a in &mut self.actors {
            if let Some(c) = a.child.as_mut() {
                c.stop(ACTOR_GRACE).await;
            }
        }
        let learner_pid = self.learner.as_ref().map(|l| l.pid).or(self.learner_exited);
        if let Some(l) = self.learner.as_mut() {
            l.stop(LEARNER_GRACE).await;
        }
        // The learner's own final counts; a learner that was killed wrote none, and the last
        // periodic Health reply stands.
        if let Some(last) = learner_pid.and_then(|pid| read_final_counters(&self.prep.run_dir, pid))
        {
            self.counters = last;
            // Kept over sessions: a resumed run's curriculum still counts these records' episodes.
            self.prep.progress.unused_records += last.counts.unused_records;
        }
        self.server.stop(SERVER_GRACE).await;
        let _ = std::fs::remove_file(self.prep.run_dir.join("processes.json"));
        let wall = self.wall_s();
        self.save_progress(true)?;
        let summary_path = self.prep.run_dir.join("summary.json");
        let Some(view) = self.last_view.as_ref() else {
            ending?;
            bail!("the curriculum server never answered GetState: no summary");
        };
        let (ending, failure) = match ending {
            Ok(ending) => (ending, None),
            Err(e) => (Ending::Failed, Some(e)),
        };
        let cfg = &self.prep.cfg;
        let shape = RunShape {
            train_envs: u64::from(cfg.env.num_envs),
            horizon: u64::from(cfg.env.max_episode_steps),
            batch_records: u64::from(cfg.service.transition_batch),
        };
        let mut summary = summarize(
            view,
            &self.evals,
            self.counters,
            &self.prep.progress,
            shape,
            wall,
            ending,
        );
        if let Some(e) = failure {
            summary.error = Some(format!("{e:#}"));
            write_json(&summary_path, &summary)?;
            return Err(e.context(format!(
                "the run failed (its summary is in {})",
                summary_path.display()
            )));
        }
        write_json(&summary_path, &summary)?;
        println!("{}", serde_json::to_string_pretty(&summary)?);
        match ending {
            Ending::Interrupted => eprintln!(
                "interrupted: continue with `rfcl train --resume {}`",
                self.prep.run_dir.display()
            ),
            Ending::Failed => unreachable!("a failure returned above"),
            Ending::Budget | Ending::EvalSuccess | Ending::Stage1Done => eprintln!(
                "run finished ({}); summary in {}",
                match ending {
                    Ending::Budget => "step budget used",
                    Ending::Stage1Done => "stage 1 ended under train.stage_1_only",
                    _ => "eval success reached",
                },
                self.prep.run_dir.join("summary.json").display()
            ),
        }
        Ok(summary)
    }
}

/// The counters the learner with `pid` wrote when it stopped cleanly
/// ([`FINAL_COUNTERS_FILE`]); `None` when it wrote none (killed) or the file is an earlier
/// process's.
fn read_final_counters(run_dir: &Path, pid: u32) -> Option<LearnerCounters> {
    let path = run_dir.join(FINAL_COUNTERS_FILE);
    let last: FinalCounters = serde_json::from_slice(&std::fs::read(&path).ok()?)
        .inspect_err(|e| tracing::warn!("reading {}: {e}", path.display()))
        .ok()?;
    (last.pid == pid).then_some(LearnerCounters {
        source: CountersSource::Final,
        counts: last.counts,
    })
}

/// The port of `host:port` or `http://host:port/`.
fn port_of(addr: &str) -> Result<u16> {
    addr.trim_end_matches('/')
        .rsplit(':')
        .next()
        .and_then(|p| p.parse().ok())
        .with_context(|| format!("no port in the service address {addr:?}"))
}

fn format_eval(e: &CompleteEval) -> String {
    format!(
        "eval at {} env steps (policy v{}): success {:.0}% at the end, {:.0}% once, mean return \
         {:.1} ({} episodes)",
        e.env_steps,
        e.policy_version,
        100.0 * e.success_at_end,
        100.0 * e.success_once,
        e.mean_return,
        e.episodes
    )
}

fn channel(url: &str) -> Result<Channel> {
    Ok(tonic::transport::Endpoint::from_shared(url.to_string())
        .with_context(|| format!("invalid address {url}"))?
        .connect_timeout(Duration::from_secs(3))
        .connect_lazy())
}

/// The progress bar on a terminal; a status line every 15 s elsewhere (logs, tests).
struct Bar {
    bar: Option<ProgressBar>,
    total: u64,
    last_line: std::cell::Cell<Option<Instant>>,
}

impl Bar {
    fn new(total: u64) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::new(total);
            bar.set_style(
                ProgressStyle::with_template(
                    "{bar:30.cyan/blue} {human_pos}/{human_len} env steps | {msg} | \
                     {elapsed_precise} elapsed, ETA {eta}",
                )
                .expect("a valid template"),
            );
            bar
        });
        Self {
            bar,
            total,
            last_line: std::cell::Cell::new(None),
        }
    }

    fn update(&self, env_steps: u64, msg: String) {
        match &self.bar {
            Some(bar) => {
                bar.set_position(env_steps.min(self.total));
                bar.set_message(msg);
            }
            None => {
                let due = self
                    .last_line
                    .get()
                    .is_none_or(|t| t.elapsed() >= Duration::from_secs(15));
                if due {
                    self.last_line.set(Some(Instant::now()));
                    eprintln!("{env_steps}/{} env steps | {msg}", self.total);
                }
            }
        }
    }

    fn println(&self, line: impl AsRef<str>) {
        match &self.bar {
            Some(bar) => bar.println(line.as_ref()),
            None => eprintln!("{}", line.as_ref()),
        }
    }

    fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

/// The run's state from its curriculum server (GetState), `None` when the server does not answer
/// within 5 s or its reply is not a run state.
pub async fn fetch_run_state(client: &mut CurriculumClient<AuthChannel>) -> Option<RunState> {
    let reply = tokio::time::timeout(
        Duration::from_secs(5),
        client.get_state(v1::GetStateRequest {}),
    )
    .await
    .ok()?
    .ok()?;
    rfcl_proto::convert::run_state(reply.get_ref()).ok()
}
