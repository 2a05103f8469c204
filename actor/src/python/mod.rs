//! Simulators written in Python (ManiSkill3, MetaWorld, Adroit: spec 7.1-7.4) as [`Env`]s.
//!
//! A [`PythonEnv`] drives one `rfcl-sim-worker` child process, which embeds Python (pyo3) and
//! serves one adapter of `python/rfcl_sim/adapters` (`rfcl_sim.adapters.make(suite, env_id,
//! **options)`) over its stdin/stdout with the binary frames of [`protocol`]. The bridge knows no
//! suite: everything suite-specific (dims, horizon, state layout) comes from the adapter's hello.
//!
//! **Why a process per env, not Python inside the actor.** Measured on PickCube-v1 (2-core CPU,
//! benches/RESULTS.md): the pipe costs a few percent of a ManiSkill step, which is dominated by
//! the simulator and its Python. In exchange, a SAPIEN segfault, an abort in a C extension or a
//! leak kills one worker, not the actor, its policy and its connections; the actor also links
//! neither libpython nor a second copy of libtorch (ManiSkill imports Python torch, and two libtorch copies in one
//! process conflict), and K envs step on K interpreters without sharing a GIL.
//!
//! **Failures.**
//! * A Python exception becomes [`EnvError::Simulator`] carrying the Python traceback; an
//!   `AdapterError` (bad input) keeps the adapter's message. The worker lives on.
//! * A worker that dies (EOF on its stdout, a broken pipe) or does not answer within
//!   [`CALL_DEADLINE`] is **reported** (its exit status or signal and the last lines of its
//!   stderr, logged at error level), **restarted**, and the episode in flight is **replayed** on the
//!   new worker: the same reset (seed, options, state), then the same actions; then the failed
//!   call is tried once more. The actor never sees the crash unless it repeats; the count is
//!   [`Env::restarts`], which the actor's episode reports carry to the curriculum dashboard and
//!   the run's summary. The replayed physics runs in a fresh scene, so the continued episode
//!   matches the lost one up to the simulator's warm-start caches, not bit for bit.
//! * A crash that repeats during the retry is returned as [`EnvError::Simulator`]; the actor then
//!   stops with that error, `rfcl train` respawns it and the curriculum server expires (and counts)
//!   its open leases.
//!
//! [`Env::get_state`] cannot return an error: it recovers as above and panics, naming the
//! failure, if that is impossible (it is used by tests and tools, not on the rollout path).
pub mod process;
pub mod protocol;

use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::time::Duration;

use rfcl_core::config::{EnvConfig, Suite};

use crate::env::{Env, EnvError, StateKind, StateLayout, StepOutcome};
use process::{describe_exit, Failure, WorkerProcess};
use protocol::{Frame, Hello};

/// The worker binary, built next to `actor` and `rfcl`.
pub const WORKER_BIN: &str = "rfcl-sim-worker";
/// Overrides where the worker binary is.
pub const WORKER_ENV: &str = "RFCL_SIM_WORKER";
/// How long a worker may take to import its simulator and make its env (a cold import of
/// ManiSkill and torch takes seconds; many workers starting at once on 2 cores take much longer).
pub const START_DEADLINE: Duration = Duration::from_secs(300);
/// How long one reset, step or state query may take before the worker counts as hung.
pub const CALL_DEADLINE: Duration = Duration::from_secs(120);

/// The adapter option that makes its simulator render (frame side in pixels).
pub const RENDER_SIZE: &str = "render_size";

/// Why a Python env could not be made or did not answer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PythonEnvError {
    #[error(
        "the simulator worker binary {WORKER_BIN} was not found (looked in {looked}); build it \
         with `cargo build --release -p rfcl-actor` or set {WORKER_ENV}"
    )]
    NoWorkerBinary { looked: String },
    #[error("starting {program} for {env_id}: {reason}")]
    Spawn {
        program: String,
        env_id: String,
        reason: String,
    },
    #[error("{env_id}: the adapter refused the input: {message}")]
    BadInput { env_id: String, message: String },
    #[error("{env_id}: Python raised an exception:\n{traceback}")]
    Python { env_id: String, traceback: String },
    #[error(
        "the {suite} worker of {env_id} (pid {pid}) {how} during {during}; the last lines of its \
         stderr:\n{stderr_tail}"
    )]
    Crashed {
        suite: String,
        env_id: String,
        pid: u32,
        how: String,
        during: &'static str,
        stderr_tail: String,
    },
    #[error("{env_id}: the worker's answer to {during} is malformed: {reason}")]
    Protocol {
        env_id: String,
        during: &'static str,
        reason: String,
    },
}

impl From<PythonEnvError> for EnvError {
    fn from(e: PythonEnvError) -> Self {
        match e {
            PythonEnvError::BadInput { message, .. } => {
                EnvError::InvalidOptions { reason: message }
            }
            other => EnvError::Simulator {
                message: other.to_string(),
            },
        }
    }
}

/// What a worker serves: `rfcl_sim.adapters.make(suite, env_id, **options)`.
#[derive(Debug, Clone, PartialEq)]
pub struct WorkerSpec {
    pub suite: String,
    pub env_id: String,
    /// The adapter's keyword arguments (a JSON object).
    pub options: serde_json::Value,
    pub program: PathBuf,
}

impl WorkerSpec {
    /// The worker for a run's env section: `max_episode_steps`, and `control_mode` and
    /// `env_kwargs` where set, become the adapter's options.
    pub fn from_env_config(env: &EnvConfig) -> Result<Self, PythonEnvError> {
        Ok(WorkerSpec {
            suite: suite_name(env.suite),
            env_id: env.env_id.clone(),
            options: env_options(env),
            program: worker_program()?,
        })
    }

    /// The same worker with its simulator rendering square frames of `side` pixels
    /// ([`Env::render`]).
    pub fn with_render_size(mut self, side: u32) -> Self {
        if let Some(options) = self.options.as_object_mut() {
            options.insert(RENDER_SIZE.into(), side.into());
        }
        self
    }

    fn args(&self) -> Vec<String> {
        vec![
            "--suite".into(),
            self.suite.clone(),
            "--env-id".into(),
            self.env_id.clone(),
            "--options".into(),
            self.options.to_string(),
        ]
    }
}

/// The keyword arguments an adapter is made with (`rfcl_sim.adapters.make`), from the run's env
/// config: `max_episode_steps`, and `control_mode`, `env_kwargs`, `imports` and `success` where
/// given.
pub fn env_options(env: &EnvConfig) -> serde_json::Value {
    let mut options = serde_json::Map::new();
    options.insert("max_episode_steps".into(), env.max_episode_steps.into());
    if let Some(mode) = &env.control_mode {
        options.insert("control_mode".into(), mode.clone().into());
    }
    if !env.env_kwargs.is_empty() {
        options.insert("env_kwargs".into(), env.env_kwargs.clone().into());
    }
    if !env.imports.is_empty() {
        options.insert("imports".into(), env.imports.clone().into());
    }
    if let Some(success) = &env.success {
        options.insert("success".into(), success.clone().into());
    }
    options.into()
}

/// The config name of a suite (`maniskill3`, ...).
pub fn suite_name(suite: Suite) -> String {
    serde_json::to_value(suite)
        .ok()
        .and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_else(|| format!("{suite:?}").to_lowercase())
}

/// `$RFCL_SIM_WORKER`, else `rfcl-sim-worker` beside the running binary, else one directory up
/// (test binaries live in `target/<profile>/deps`).
pub fn worker_program() -> Result<PathBuf, PythonEnvError> {
    if let Some(p) = std::env::var_os(WORKER_ENV).filter(|p| !p.is_empty()) {
        return Ok(PathBuf::from(p));
    }
    let exe = std::env::current_exe().ok();
    let dir = exe.as_deref().and_then(Path::parent);
    let candidates: Vec<PathBuf> = dir
        .into_iter()
        .flat_map(|d| [Some(d.to_path_buf()), d.parent().map(Path::to_path_buf)])
        .flatten()
        .map(|d| d.join(WORKER_BIN))
        .collect();
    candidates
        .iter()
        .find(|p| p.is_file())
        .cloned()
        .ok_or_else(|| PythonEnvError::NoWorkerBinary {
            looked: candidates
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", "),
        })
}

/// Starts a worker for `spec`, reads its hello, and stops it: the adapter's description.
pub fn describe(spec: &WorkerSpec) -> Result<Hello, PythonEnvError> {
    Ok(Worker::start(spec)?.hello)
}

/// The dims and state layout of `spec`'s env, from a worker started and stopped for the purpose.
pub fn describe_layout(spec: &WorkerSpec) -> Result<(usize, usize, StateLayout), PythonEnvError> {
    let hello = describe(spec)?;
    let layout = layout_of(spec, &hello)?;
    Ok((hello.obs_dim, hello.action_dim, layout))
}

/// The episode in flight, enough to rebuild it on a new worker.
#[derive(Debug, Clone)]
struct EpisodeLog {
    reset: Vec<u8>,
    actions: Vec<Vec<u8>>,
}

/// A started worker and its hello.
struct Worker {
    process: WorkerProcess,
    hello: Hello,
}

impl Worker {
    fn start(spec: &WorkerSpec) -> Result<Worker, PythonEnvError> {
        let label = format!("{}-worker", spec.env_id);
        let mut process =
            WorkerProcess::spawn(&spec.program, &spec.args(), label).map_err(|e| {
                PythonEnvError::Spawn {
                    program: spec.program.display().to_string(),
                    env_id: spec.env_id.clone(),
                    reason: e.to_string(),
                }
            })?;
        let frame = match process.call(None, START_DEADLINE) {
            Ok(frame) => frame,
            Err(failure) => return Err(crash_report(spec, &mut process, failure, "start-up")),
        };
        let payload = ok_payload(spec, frame)?;
        let hello: Hello =
            serde_json::from_slice(&payload).map_err(|e| PythonEnvError::Protocol {
                env_id: spec.env_id.clone(),
                during: "start-up",
                reason: format!("hello is not the expected JSON: {e}"),
            })?;
        Ok(Worker { process, hello })
    }
}

/// The answer's payload, or the Python error it carries.
fn ok_payload(spec: &WorkerSpec, frame: Frame) -> Result<Vec<u8>, PythonEnvError> {
    let text = || String::from_utf8_lossy(&frame.payload).into_owned();
    match frame.tag {
        protocol::STATUS_OK => Ok(frame.payload),
        protocol::STATUS_BAD_INPUT => Err(PythonEnvError::BadInput {
            env_id: spec.env_id.clone(),
            message: text(),
        }),
        protocol::STATUS_EXCEPTION => Err(PythonEnvError::Python {
            env_id: spec.env_id.clone(),
            traceback: text(),
        }),
        other => Err(PythonEnvError::Protocol {
            env_id: spec.env_id.clone(),
            during: "a call",
            reason: format!("unknown status {other}"),
        }),
    }
}

fn crash_report(
    spec: &WorkerSpec,
    process: &mut WorkerProcess,
    failure: Failure,
    during: &'static str,
) -> PythonEnvError {
    let pid = process.pid();
    let (status, stderr_tail) = process.post_mortem();
    let how = match failure {
        Failure::Died => describe_exit(status),
        Failure::TimedOut(d) => format!("did not answer within {} s and was killed", d.as_secs()),
        Failure::Corrupt(why) => format!("wrote a corrupt frame ({why}) and was killed"),
    };
    PythonEnvError::Crashed {
        suite: spec.suite.clone(),
        env_id: spec.env_id.clone(),
        pid,
        how,
        during,
        stderr_tail,
    }
}

struct Inner {
    /// `None` after a crash that could not be recovered: the next call starts a new worker.
    worker: Option<WorkerProcess>,
    episode: Option<EpisodeLog>,
    restarts: u64,
}

/// An [`Env`] served by a Python worker process (module docs).
pub struct PythonEnv {
    spec: WorkerSpec,
    hello: Hello,
    layout: StateLayout,
    call_deadline: Duration,
    inner: RefCell<Inner>,
}

impl PythonEnv {
    /// Starts the worker and resets it to `seed`, so that its RNG chain starts there (the
    /// [`Env::reset_to_seed`] contract).
    pub fn start(spec: WorkerSpec, seed: u64) -> Result<Self, PythonEnvError> {
        let Worker { process, hello } = Worker::start(&spec)?;
        let layout = layout_of(&spec, &hello)?;
        let env = PythonEnv {
            spec,
            hello,
            layout,
            call_deadline: CALL_DEADLINE,
            inner: RefCell::new(Inner {
                worker: Some(process),
                episode: None,
                restarts: 0,
            }),
        };
        env.call(
            protocol::OP_RESET,
            &protocol::reset_request(Some(seed), "{}", &[]),
            "reset",
        )?;
        Ok(env)
    }

    /// The adapter's description (dims, horizon, layout, Python version).
    pub fn hello(&self) -> &Hello {
        &self.hello
    }

    /// How long one call may take before the worker counts as hung (default [`CALL_DEADLINE`]).
    pub fn set_call_deadline(&mut self, deadline: Duration) {
        self.call_deadline = deadline;
    }

    /// The current worker's pid (`None` between a failed restart and the next call).
    pub fn worker_pid(&self) -> Option<u32> {
        self.inner.borrow().worker.as_ref().map(WorkerProcess::pid)
    }

    /// [`Env::get_state`] with its error.
    pub fn try_get_state(&self) -> Result<Vec<f32>, PythonEnvError> {
        let payload = self.call(protocol::OP_GET_STATE, &[], "get_state")?;
        self.floats(&payload, self.layout.dim(), "get_state")
    }

    /// One request, with the recovery of the module docs.
    fn call(
        &self,
        op: u8,
        payload: &[u8],
        during: &'static str,
    ) -> Result<Vec<u8>, PythonEnvError> {
        let mut inner = self.inner.borrow_mut();
        if inner.worker.is_none() {
            self.restart(&mut inner, op != protocol::OP_RESET)?;
        }
        let worker = inner.worker.as_mut().expect("started above");
        let first = match worker.call(Some((op, payload)), self.call_deadline) {
            Ok(frame) => return self.answer(&mut inner, op, payload, frame),
            Err(failure) => failure,
        };
        let crash = crash_report(&self.spec, worker, first, during);
        inner.worker = None;
        tracing::error!(
            env = %self.spec.env_id,
            restarts = inner.restarts + 1,
            "{crash}\n(restarting the worker and replaying the episode in flight)"
        );
        self.restart(&mut inner, op != protocol::OP_RESET)
            .map_err(|e| with_cause(crash.clone(), e))?;
        let worker = inner.worker.as_mut().expect("restarted above");
        match worker.call(Some((op, payload)), self.call_deadline) {
            Ok(frame) => self.answer(&mut inner, op, payload, frame),
            Err(again) => {
                let second = crash_report(&self.spec, worker, again, during);
                inner.worker = None;
                Err(second)
            }
        }
    }

    /// Decodes an answer and keeps the episode log up to date.
    fn answer(
        &self,
        inner: &mut Inner,
        op: u8,
        payload: &[u8],
        frame: Frame,
    ) -> Result<Vec<u8>, PythonEnvError> {
        let out = ok_payload(&self.spec, frame)?;
        match op {
            protocol::OP_RESET => {
                inner.episode = Some(EpisodeLog {
                    reset: payload.to_vec(),
                    actions: Vec::new(),
                })
            }
            protocol::OP_STEP => {
                if let Some(e) = inner.episode.as_mut() {
                    e.actions.push(payload.to_vec());
                }
            }
            _ => {}
        }
        Ok(out)
    }

    /// A new worker; with `replay`, the episode in flight is rebuilt on it.
    fn restart(&self, inner: &mut Inner, replay: bool) -> Result<(), PythonEnvError> {
        let Worker { mut process, hello } = Worker::start(&self.spec)?;
        if hello != self.hello {
            return Err(PythonEnvError::Protocol {
                env_id: self.spec.env_id.clone(),
                during: "restart",
                reason: format!(
                    "the restarted adapter describes itself differently ({hello:?} vs {:?})",
                    self.hello
                ),
            });
        }
        inner.restarts += 1;
        if let (true, Some(episode)) = (replay, inner.episode.as_ref()) {
            let requests = std::iter::once((protocol::OP_RESET, &episode.reset))
                .chain(episode.actions.iter().map(|a| (protocol::OP_STEP, a)));
            for (op, payload) in requests {
                let frame = match process.call(Some((op, payload)), self.call_deadline) {
                    Ok(frame) => frame,
                    Err(f) => return Err(crash_report(&self.spec, &mut process, f, "replay")),
                };
                ok_payload(&self.spec, frame)?;
            }
            tracing::warn!(
                env = %self.spec.env_id,
                steps = episode.actions.len(),
                "worker restarted; the episode in flight was replayed"
            );
        }
        inner.worker = Some(process);
        Ok(())
    }

    fn floats(
        &self,
        bytes: &[u8],
        n: usize,
        during: &'static str,
    ) -> Result<Vec<f32>, PythonEnvError> {
        match protocol::get_f32s(bytes) {
            Some(v) if v.len() == n => Ok(v),
            got => Err(PythonEnvError::Protocol {
                env_id: self.spec.env_id.clone(),
                during,
                reason: format!(
                    "expected {n} float32 values, got {}",
                    got.map_or_else(|| format!("{} bytes", bytes.len()), |v| v.len().to_string())
                ),
            }),
        }
    }

    fn reset(
        &mut self,
        seed: Option<u64>,
        options: &serde_json::Value,
        state: &[f32],
    ) -> Result<Vec<f32>, EnvError> {
        if !(options.is_null() || options.is_object()) {
            return Err(EnvError::InvalidOptions {
                reason: format!("expected a JSON object, got {options}"),
            });
        }
        let options = if options.is_null() {
            "{}".to_owned()
        } else {
            options.to_string()
        };
        let payload = protocol::reset_request(seed, &options, state);
        let out = self.call(protocol::OP_RESET, &payload, "reset")?;
        Ok(self.floats(&out, self.hello.obs_dim, "reset")?)
    }
}

/// `first` with what went wrong while recovering from it.
fn with_cause(first: PythonEnvError, recovery: PythonEnvError) -> PythonEnvError {
    match first {
        PythonEnvError::Crashed {
            suite,
            env_id,
            pid,
            how,
            during,
            stderr_tail,
        } => PythonEnvError::Crashed {
            suite,
            env_id,
            pid,
            how,
            during,
            stderr_tail: format!("{stderr_tail}\n(restarting it failed: {recovery})"),
        },
        other => other,
    }
}

fn layout_of(spec: &WorkerSpec, hello: &Hello) -> Result<StateLayout, PythonEnvError> {
    let mut parts = Vec::with_capacity(hello.state_layout.len());
    for (name, kind, len) in &hello.state_layout {
        let kind: StateKind = serde_json::from_value(serde_json::Value::String(kind.clone()))
            .map_err(|_| PythonEnvError::Protocol {
                env_id: spec.env_id.clone(),
                during: "start-up",
                reason: format!(
                    "state entry {name} has kind '{kind}', expected flat, actor, articulation or field"
                ),
            })?;
        parts.push((name.clone(), kind, *len));
    }
    Ok(StateLayout::from_parts(parts))
}

impl Env for PythonEnv {
    fn obs_dim(&self) -> usize {
        self.hello.obs_dim
    }

    fn action_dim(&self) -> usize {
        self.hello.action_dim
    }

    fn horizon(&self) -> usize {
        self.hello.horizon
    }

    fn state_layout(&self) -> &StateLayout {
        &self.layout
    }

    fn reset_to_seed(
        &mut self,
        seed: Option<u64>,
        options: &serde_json::Value,
    ) -> Result<Vec<f32>, EnvError> {
        self.reset(seed, options, &[])
    }

    fn reset_to_state(
        &mut self,
        seed: Option<u64>,
        options: &serde_json::Value,
        state: &[f32],
    ) -> Result<Vec<f32>, EnvError> {
        if state.len() != self.layout.dim() {
            return Err(EnvError::StateLen {
                expected: self.layout.dim(),
                got: state.len(),
            });
        }
        self.reset(seed, options, state)
    }

    fn step(&mut self, action: &[f32]) -> Result<StepOutcome, EnvError> {
        if action.len() != self.hello.action_dim {
            return Err(EnvError::ActionDim {
                expected: self.hello.action_dim,
                got: action.len(),
            });
        }
        if let Some((index, &value)) = action.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(EnvError::NonFiniteAction { index, value });
        }
        let mut payload = Vec::with_capacity(4 * action.len());
        protocol::put_f32s(&mut payload, action);
        let out = self.call(protocol::OP_STEP, &payload, "step")?;
        let Some((&flag, obs)) = out.split_first() else {
            return Err(PythonEnvError::Protocol {
                env_id: self.spec.env_id.clone(),
                during: "step",
                reason: "empty answer".into(),
            }
            .into());
        };
        Ok(StepOutcome {
            obs: self.floats(obs, self.hello.obs_dim, "step")?,
            success: flag != 0,
        })
    }

    fn get_state(&self) -> Vec<f32> {
        self.try_get_state()
            .unwrap_or_else(|e| panic!("PythonEnv::get_state: {e}"))
    }

    /// The adapter's renderer: only workers made with [`WorkerSpec::with_render_size`] have one.
    fn render(&mut self) -> Result<crate::video::Frame, EnvError> {
        if self.spec.options.get(RENDER_SIZE).is_none() {
            return Err(EnvError::NoRenderer {
                hint: format!(
                    " ({} was started without `{RENDER_SIZE}`, which makes the simulator render)",
                    self.spec.env_id
                ),
            });
        }
        let out = self.call(protocol::OP_RENDER, &[], "render")?;
        protocol::render_answer(&out).map_err(|reason| {
            EnvError::from(PythonEnvError::Protocol {
                env_id: self.spec.env_id.clone(),
                during: "render",
                reason,
            })
        })
    }

    /// Times the worker was restarted after a crash or a hang.
    fn restarts(&self) -> u64 {
        self.inner.borrow().restarts
    }
}
