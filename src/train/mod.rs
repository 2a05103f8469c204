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
//!   summary say which process, why and what was rolled back; a service or actor that keeps dying
//!   stops the run with its error (the last lines of its log). The actors and the other service
//!   reconnect by themselves;
//! * the run ends when the learner exits after its budget, or when the mean success of the last 5
//!   evaluations reaches `service.stop_at_eval_success`; Ctrl-C / SIGTERM stops it cleanly, and
//!   `--resume RUN_DIR` continues it;
//! * at the end it writes and prints `RUN_DIR/summary.json` (also when a failure ends the run:
//!   `ending: failed` with the `error`).
//!
//! Files in the run directory beside the services' own: `config.yml` (resolved), `logs/<child>.log`,
//! `processes.json` (while a session runs: the services' addresses, every child's name and pid),
//! `train_progress.json` (wall time of earlier sessions, eval completion times), `summary.json`.
//!
//! The parts: [`supervisor`] keeps the process table (start, reap, respawn, stop); [`policy`]
//! decides, purely, what a death or a silence leads to; [`monitor`] polls the services' Health and
//! GetState; [`display`] draws the bar and writes the lines; [`finish`] writes the summary;
//! [`progress`] is the run's bookkeeping across sessions. [`Session`] joins them in one loop.
mod children;
mod display;
mod finish;
mod monitor;
mod policy;
pub mod progress;
mod supervisor;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use rfcl_core::config::{resolve_file, to_yaml, RunConfig};
use rfcl_core::run_lock::RunDirLock;
use rfcl_proto::auth::{self, ClientAuth, Token};
use rfcl_proto::v1::curriculum_client::CurriculumClient;
use rfcl_proto::v1::learner_client::LearnerClient;
use rfcl_runtime::Signals;

use children::{describe, find_setpriv, Launcher};
use display::{eval_line, silence_line, status, Bar};
use finish::{read_final_counters, Outcome};
pub use monitor::fetch_run_state;
use monitor::{channel, Monitor};
use policy::{Service, ServiceDecision, SilenceAction, SERVICE_RESTART_WINDOW_S};
use progress::{
    CompleteEval, Ending, EvalTracker, RolledBack, RunProgress, ServiceRestart, Summary,
};
use supervisor::{ActorExit, ServiceInputs, Supervisor};

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

/// A running session: the process table, what is known of the services, the display, and the
/// run's progress. Its loop ([`Session::supervise`]) turns what the monitor sees into the
/// supervisor's actions, as the restart policy decides.
struct Session {
    prep: Prepared,
    supervisor: Supervisor,
    monitor: Monitor,
    bar: Bar,
    started: Instant,
    /// The pid of a learner that ended the run by exiting by itself.
    learner_exited: Option<u32>,
    /// The service killed for not answering, and how long it had been silent (the cause of its
    /// restart).
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

impl Session {
    async fn start(prep: Prepared, launcher: Launcher) -> Result<Session> {
        let token = launcher.token.clone();
        let (mut supervisor, learner_line) = Supervisor::start(
            ServiceInputs {
                cfg: &prep.cfg,
                run_dir: &prep.run_dir,
                config_path: &prep.config_path,
                demos: &prep.demos,
                learner_threads: prep.learner_threads,
                resume: prep.resume,
            },
            launcher,
        )
        .await?;
        let addrs = supervisor.addrs.clone();
        println!("dashboard: {}", addrs.dashboard);
        eprintln!(
            "curriculum server at {}, learner at {}",
            addrs.curriculum, addrs.learner
        );
        if let Some(metrics) = learner_line.field("metrics") {
            eprintln!("learner metrics (Prometheus): {metrics}");
        }
        let client_auth = ClientAuth::plain(token);
        let curriculum = CurriculumClient::new(client_auth.wrap(channel(&addrs.curriculum)?))
            .max_decoding_message_size(64 << 20);
        let learner = LearnerClient::new(client_auth.wrap(channel(&addrs.learner)?));
        let episodes_needed = rfcl_actor::eval::episodes_per_eval(&prep.cfg);
        let evals = EvalTracker::new(episodes_needed, &prep.progress.evals);
        supervisor.start_actors()?;
        Ok(Session {
            bar: Bar::new(prep.cfg.train.steps),
            monitor: Monitor::new(curriculum, learner, evals),
            supervisor,
            started: Instant::now(),
            learner_exited: None,
            killed_silent: None,
            prep,
        })
    }

    fn wall_s(&self) -> f64 {
        self.prep.progress.earlier_sessions_s + self.started.elapsed().as_secs_f64()
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
            if let Some(status) = self.supervisor.try_wait(Service::Curriculum) {
                if let Some(ending) = self.restart(Service::Curriculum, status, signals).await? {
                    return Ok(ending);
                }
            }
            if let Some(status) = self.supervisor.try_wait(Service::Learner) {
                if status.success() {
                    self.learner_exited = self.supervisor.learner_ended();
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
            self.reap_actors()?;
            let answered = self.monitor.poll_health().await;
            self.heard(Service::Learner, answered);
            if ticks % STATE_EVERY == 1 {
                let answered = self.poll_state().await;
                self.heard(Service::Curriculum, answered);
                if self
                    .monitor
                    .evals
                    .reached(self.prep.cfg.service.stop_at_eval_success)
                {
                    return Ok(Ending::EvalSuccess);
                }
            }
            if ticks.is_multiple_of(PROGRESS_EVERY) {
                self.save_progress_or_warn();
            }
            self.draw();
            if self.supervisor.train_actors_done() {
                self.bar
                    .println("every actor finished: the curriculum hands out no more leases");
                return Ok(self.ended_by_itself().await);
            }
        }
    }

    /// Restarts `service`, which died with `status`, from its last snapshot or checkpoint: after
    /// the policy's backoff, on the port it had, until it is ready again or has died too often
    /// (an error). Records the restart with what it rolled back. `Some(Interrupted)` when Ctrl-C
    /// came first.
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
        let mut tail = self.supervisor.log_tail(service);
        // A full disk kills every restart the same way: say so instead of retrying.
        if let Some(short) = children::short_of_space(&self.prep.run_dir) {
            bail!(
                "the {name} died ({cause}) with {short}: its checkpoints and logs cannot be \
                 written there. Free space, then continue with `rfcl train --resume {}`{tail}",
                self.prep.run_dir.display()
            );
        }
        let before = self.monitor.rollback_counters();
        let (child, line) = loop {
            let delay = match self.supervisor.policy.service_died(service, self.wall_s()) {
                ServiceDecision::Restart { delay_s } => delay_s,
                ServiceDecision::GiveUp { deaths } => bail!(
                    "the {name} died {deaths} times within {SERVICE_RESTART_WINDOW_S} s (last: \
                     {cause}); stopping the run{tail}"
                ),
            };
            self.bar.println(format!(
                "the {name} died ({cause}); restarting it in {delay} s from its last {}{tail}",
                service.saved_state()
            ));
            tokio::select! {
                _ = tokio::time::sleep(Duration::from_secs(delay)) => {}
                _ = signals.recv() => return Ok(Some(Ending::Interrupted)),
            }
            let mut child = self.supervisor.spawn_again(service)?;
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
        self.supervisor.replace(service, child)?;
        match service {
            Service::Curriculum => self.take_state().await,
            Service::Learner => {
                self.monitor.rate.restart();
                for _ in 0..10 {
                    if self.monitor.poll_health().await {
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
        let rolled_back = RolledBack::between(before, self.monitor.rollback_counters());
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
        self.save_progress_or_warn();
        Ok(None)
    }

    /// Why a run that ended by itself ended: the curriculum server's stop rule (the evals reached
    /// `service.stop_at_eval_success`), the end of stage 1 under `train.stage_1_only`, or the
    /// budget.
    async fn ended_by_itself(&mut self) -> Ending {
        self.poll_state().await;
        let stage_1_ended = self
            .monitor
            .last_view
            .as_ref()
            .is_some_and(|v| v.stage_1_env_steps.is_some());
        if self
            .monitor
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
            || !self.monitor.evals.final_eval_pending(
                last.counts.env_steps,
                cfg.sac.eval_freq,
                cfg.sac.num_seed_steps,
            )
        {
            return true;
        }
        self.supervisor.stop_train_actors().await;
        self.bar.println(format!(
            "train.steps used: waiting for the evaluation of the final policy (version \
             {final_policy}, {} env steps)",
            last.counts.env_steps
        ));
        let mut reported = self.monitor.eval_episodes_reported();
        let mut last_news = Instant::now();
        let mut tick = tokio::time::interval(POLL_EVERY);
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                _ = signals.recv() => return false,
            }
            self.poll_state().await;
            if self
                .monitor
                .evals
                .evals()
                .iter()
                .any(|e| e.point.policy_version >= final_policy)
            {
                return true;
            }
            let now_reported = self.monitor.eval_episodes_reported();
            if now_reported > reported {
                (reported, last_news) = (now_reported, Instant::now());
            }
            let why = if !self.supervisor.eval_actors_running() {
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

    /// Reaps the actors that exited, says what became of them and counts the respawns.
    fn reap_actors(&mut self) -> Result<()> {
        for exit in self.supervisor.reap_actors(self.wall_s())? {
            match exit {
                ActorExit::Finished { name } => {
                    self.bar.println(format!("{name} finished (exit status 0)"))
                }
                ActorExit::Respawned {
                    name,
                    pid,
                    cause,
                    tail,
                } => {
                    self.prep.progress.actor_respawns += 1;
                    self.bar.println(format!(
                        "{name} died ({cause}); respawned it (pid {pid}){tail}"
                    ));
                }
            }
        }
        Ok(())
    }

    /// True when the curriculum server answered; completed evaluations are printed and saved.
    async fn poll_state(&mut self) -> bool {
        let Some(fresh) = self.monitor.poll_state(self.wall_s()).await else {
            return false;
        };
        if self.record_evals(fresh) {
            self.save_progress_or_warn();
        }
        true
    }

    /// Takes the curriculum server's state, if it answers, and records the evals it completes.
    async fn take_state(&mut self) {
        if let Some(fresh) = self.monitor.poll_state(self.wall_s()).await {
            self.record_evals(fresh);
        }
    }

    /// Prints and records completed evaluations; true if there were any.
    fn record_evals(&mut self, fresh: Vec<CompleteEval>) -> bool {
        let any = !fresh.is_empty();
        for eval in fresh {
            self.bar.println(eval_line(&eval));
            self.prep.progress.evals.push(eval);
        }
        any
    }

    /// Counts a service's answer or silence: says so once it has been silent a while, and kills
    /// it at `service.hang_timeout_s`, so that the supervision restarts it as a dead one.
    fn heard(&mut self, service: Service, answered: bool) {
        let Some(pid) = self.supervisor.child(service).map(|c| c.pid) else {
            return;
        };
        let timeout = self.prep.cfg.service.hang_timeout_s;
        let action = self
            .monitor
            .heard(service, answered, self.wall_s(), timeout);
        if let Some(line) = silence_line(service.name(), pid, action, timeout) {
            self.bar.println(line);
        }
        if let SilenceAction::Kill(s) = action {
            if let Some(child) = self.supervisor.child(service) {
                child.signal(rustix::process::Signal::KILL);
            }
            self.killed_silent = Some((service, s));
        }
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

    fn save_progress_or_warn(&self) {
        if let Err(e) = self.save_progress(false) {
            self.bar.println(format!("warning: {e:#}"));
        }
    }

    fn draw(&self) {
        self.bar.update(
            self.monitor.counters.counts.env_steps,
            status(
                self.monitor.stage(),
                self.monitor.evals.last().as_ref(),
                self.monitor.rate.per_s,
            ),
        );
    }

    /// Stops every child in order (actors, learner, curriculum server) after taking the
    /// curriculum's final state, then writes the summary. The learner's counters are its own
    /// final ones, all from one moment, so they agree with each other.
    async fn finish(mut self, ending: Result<Ending>) -> Result<Summary> {
        self.take_state().await;
        self.bar.finish();
        let learner_pid = self
            .supervisor
            .stop_actors_and_learner()
            .await
            .or(self.learner_exited);
        // The learner's own final counts; a learner that was killed wrote none, and the last
        // periodic Health reply stands.
        if let Some(last) = learner_pid.and_then(|pid| read_final_counters(&self.prep.run_dir, pid))
        {
            self.monitor.counters = last;
            // Kept over sessions: a resumed run's curriculum still counts these records' episodes.
            self.prep.progress.unused_records += last.counts.unused_records;
        }
        self.supervisor.stop_server().await;
        let wall_s = self.wall_s();
        self.save_progress(true)?;
        finish::write_summary(
            Outcome {
                cfg: &self.prep.cfg,
                run_dir: &self.prep.run_dir,
                view: self.monitor.last_view.as_ref(),
                evals: &self.monitor.evals,
                counters: self.monitor.counters,
                progress: &self.prep.progress,
                wall_s,
            },
            ending,
        )
    }
}
