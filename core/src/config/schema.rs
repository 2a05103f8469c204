//! The run configuration: every option of docs/ALGORITHM.md sections 2-8 plus the service's
//! own. Option names follow the reference implementation where the spec names them (`num_qs`,
//! `grad_updates_per_step`, `reverse_step_size`, ...) so researchers recognise them; `Default` is the
//! reference behaviour. See `docs/CONFIG.md` for the reference of every key and the deliberate
//! deviations.
use serde::{Deserialize, Serialize};

/// A fully resolved run configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunConfig {
    /// Run name; the run directory is `runs/<name>` unless given.
    pub name: String,
    /// Experiment seed: curricula, network init, actors' env seeds derive from it.
    pub seed: u64,
    /// Seed for demo selection (spec 6.1); `None` uses `seed`.
    pub demo_seed: Option<u64>,
    pub env: EnvConfig,
    pub eval_env: EvalEnvConfig,
    pub sac: SacConfig,
    pub network: NetworkConfig,
    pub train: TrainConfig,
    pub reverse: ReverseConfig,
    pub forward: ForwardConfig,
    pub service: ServiceConfig,
    pub learner: LearnerConfig,
}

/// Which simulator family runs the env.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Suite {
    /// The native Rust PointMaze (spec 7.5).
    Pointmaze,
    /// ManiSkill3 on the CPU backend (spec 7.1).
    Maniskill3,
    /// MetaWorld (spec 7.3).
    Metaworld,
    /// Adroit from gymnasium-robotics (spec 7.4).
    Adroit,
    /// Your own task: any Gymnasium env that saves and restores its state, or any MuJoCo env
    /// (docs/YOUR_TASK.md, `python/rfcl_sim/adapters/gym_envs.py`).
    Gymnasium,
}

impl Suite {
    /// Whether the suite's envs may come from modules the config imports (`env.imports`).
    pub fn takes_imports(self) -> bool {
        matches!(self, Suite::Gymnasium | Suite::Maniskill3)
    }
}

/// The training env (spec 7, 8.1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EnvConfig {
    pub env_id: String,
    pub suite: Suite,
    /// Env horizon H; the stage-1 dynamic limit is applied on top of it.
    pub max_episode_steps: u32,
    /// Train envs in total, over all actors (the reference's 8).
    pub num_envs: u32,
    /// Controller (ManiSkill: `pd_joint_delta_pos`); `None` = the suite's default.
    pub control_mode: Option<String>,
    /// Extra keyword arguments for the simulator's constructor.
    pub env_kwargs: serde_json::Map<String, serde_json::Value>,
    /// Python modules the simulator worker imports before it makes the env, e.g. the package
    /// that registers your own envs (`gymnasium` and `maniskill3` suites).
    pub imports: Vec<String>,
    /// `module:callable(env, obs, info) -> bool`: the success of an env whose step info reports
    /// none (`gymnasium` suite; `None` = the info's `success` or `is_success`).
    pub success: Option<String>,
    /// Expected observation dim; checked against demos and the env when set.
    pub obs_dim: Option<u32>,
    /// Expected action dim; checked against demos and the env when set.
    pub action_dim: Option<u32>,
}

/// The evaluation env (spec 5.7).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvalEnvConfig {
    /// Eval envs in total, over all eval actors (the reference's `num_eval_envs`).
    pub num_envs: u32,
    /// `None` = the training env's horizon.
    pub max_episode_steps: Option<u32>,
    /// Eval seeds start here (held out from the forward curriculum's levels).
    pub seed_offset: u64,
    /// Every this many evaluations, an eval actor records its first episode as a video and sends
    /// it to the curriculum server, whose dashboard links it from the eval table; 0 = never.
    pub video_every: u32,
    /// Side of the videos' square frames in pixels, for simulators that render (PointMaze is
    /// drawn at its own size).
    pub video_size: u32,
}

/// Where the SAC maths run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Device {
    Cpu,
    Cuda,
}

/// Matmul precision of the learner. `fp32` is exact; `bf16` trades precision for speed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MatmulPrecision {
    Fp32,
    Bf16,
}

/// How learner updates and env steps are paced (docs/LEARNER.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum UtdMode {
    /// Critic updates per received env step held at the configured ratio (reference behaviour).
    Sync,
    /// Actors and learner run flat out; the achieved ratio is reported.
    Async,
}

/// SAC with a Q-ensemble (spec 5, 8.1, 8.2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SacConfig {
    /// Uniform-random steps at the start of stage 1; policy-only, update-free steps at the start of
    /// stage 2 (spec 4.4, 5.4).
    pub num_seed_steps: u64,
    /// Online replay capacity in transitions, split evenly over the train envs (spec 5.5).
    pub replay_buffer_capacity: u64,
    /// Minibatch size B; each minibatch is half online, half offline (spec 5.2).
    pub batch_size: u32,
    /// Env steps per env per training iteration (1 sample-efficient, 4 fast).
    pub steps_per_env: u32,
    /// G: critic updates per iteration (spec 5.2).
    pub grad_updates_per_step: u32,
    /// F: critic updates per actor update (spec 5.2).
    pub actor_update_freq: u32,
    /// Critic members trained (deviation 2; the reference always trains 10).
    pub critic_ensemble: u32,
    /// Members the target may draw from, {0..target_pool-1}: the reference's `num_qs`.
    #[serde(alias = "num_qs")]
    pub target_pool: u32,
    /// Members drawn (without replacement) for the target minimum.
    pub num_min_qs: u32,
    /// Discount gamma.
    pub discount: f64,
    /// Polyak rate of the target critic.
    pub tau: f64,
    /// Subtract the entropy term in the target (false in every reference config).
    pub backup_entropy: bool,
    /// Learn the temperature alpha (spec 5.3).
    pub learnable_temp: bool,
    /// alpha at the start.
    pub initial_temperature: f64,
    /// `None` = -A/2 (spec 5.3).
    pub target_entropy: Option<f64>,
    /// Adam learning rates (spec 5.3).
    pub actor_lr: f64,
    pub critic_lr: f64,
    pub temp_lr: f64,
    /// Adam moments and epsilon (spec 5.3).
    pub adam_beta1: f64,
    pub adam_beta2: f64,
    pub adam_eps: f64,
    /// Evaluate every this many env steps, once past the seed steps (spec 5.7).
    pub eval_freq: u64,
    /// Env steps per eval env per evaluation (spec 5.7).
    pub eval_steps: u64,
    /// Log training metrics every this many env steps (spec 5.8).
    pub log_freq: u64,
    /// Checkpoint every this many env steps.
    pub save_freq: u64,
    /// Checkpoint also when this many seconds of wall time have passed since the last one, so a
    /// learner that dies is never far from a checkpoint (only the replay's new rows are written).
    pub save_every_s: f64,
    pub utd_mode: UtdMode,
    /// Where the learner runs the SAC maths.
    pub device: Device,
    pub matmul_precision: MatmulPrecision,
}

/// MLP shapes (spec 5.1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NetworkConfig {
    /// Hidden layer widths of the actor trunk.
    pub actor_features: Vec<u32>,
    /// Hidden layer widths of each critic.
    pub critic_features: Vec<u32>,
    /// LayerNorm before ReLU in every critic hidden layer.
    pub critic_layer_norm: bool,
    pub layer_norm_eps: f64,
    /// Range of the tanh-squashed log-std (spec 5.1).
    pub log_std_min: f64,
    pub log_std_max: f64,
}

/// Budget, demos and stage options (spec 4, 6).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    /// Total env-step budget over both stages.
    pub steps: u64,
    /// Demo file (ManiSkill trajectory HDF5 + JSON sidecar). In a file, a relative path is relative
    /// to the directory of the file that sets it (in an override, to the working directory); a
    /// resolved config holds it absolute.
    pub dataset_path: Option<String>,
    /// Demos used (spec 6.1).
    pub num_demos: u32,
    /// Shuffle the episode list before taking the first `num_demos` successful ones (spec 6.1).
    pub shuffle_demos: bool,
    /// Rescale demo actions into agent units (spec 6.4, deviation 1); `None` = off.
    pub data_action_scale: Option<f64>,
    /// Load demo transitions as stage 1's offline buffer; false = demos only for resets (spec 6.3).
    pub train_on_demo_actions: bool,
    /// Stage 2 keeps the stage-1 actor / critic (with optimiser states) (spec 4.1).
    pub load_actor: bool,
    pub load_critic: bool,
    /// The stage-1 online buffer becomes stage 2's offline buffer (spec 4.2).
    pub load_as_offline_buffer: bool,
    /// The stage-1 online buffer stays stage 2's online buffer, with no offline buffer (spec 4.2).
    pub load_as_online_buffer: bool,
    /// Evaluate on the true task distribution during stage 1 (spec 2.9).
    pub use_orig_env_for_eval: bool,
    /// Stage-1 evals start at demo state 0 (spec 2.9).
    pub eval_start_of_demos: bool,
    /// `rfcl` (the method) or `rlpd`: the RLPD baseline in the same service, with no state resets
    /// (docs/ALGORITHM.md 4, "RLPD mode").
    pub mode: TrainMode,
    /// Skip stage 1 and keep the demos as the offline buffer ("forward-only").
    pub stage_2_only: bool,
    /// Stop after stage 1.
    pub stage_1_only: bool,
}

/// What a run trains: RFCL, or the RLPD baseline (no resets to demo states; demos only as the
/// offline half of every batch).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrainMode {
    #[default]
    Rfcl,
    Rlpd,
}

/// Which stages a run goes through (spec 4): both (the default), the reverse curriculum only
/// (`train.stage_1_only`) or the forward curriculum only (`train.stage_2_only`). See
/// [`TrainConfig::stage_plan`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StagePlan {
    Both,
    ReverseOnly,
    ForwardOnly,
}

/// Per-demo or global advance rule (spec 2.6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CurriculumMethod {
    PerDemo,
    Global,
}

/// Start-step samplers (spec 2.3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StartStepSampler {
    Geometric,
    FixedPoint,
    Uniform,
    UniformSpike,
    UniformStep,
}

/// Dynamic time limit formula (spec 2.5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TimeLimitFormula {
    /// offset + floor((S_i - s) / phi).
    Reference,
    /// 1 + (T_i - s) / phi, as the paper writes it.
    Paper,
}

/// Stage 1: the per-demo reverse curriculum (spec 2). Defaults are the reference's constants.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ReverseConfig {
    /// Per-demo or global advance rule (spec 2.6).
    pub curriculum_method: CurriculumMethod,
    /// Start-step sampler (spec 2.3).
    pub start_step_sampler: StartStepSampler,
    /// Probabilities of offsets 0..k-1 of the truncated geometric sampler.
    pub geometric_probs: Vec<f64>,
    /// delta: how far t_i moves back on an advance.
    pub reverse_step_size: u32,
    /// m: the per-demo success FIFO length.
    pub per_demo_buffer_size: u32,
    /// phi; <= 0 disables the dynamic time limit.
    pub demo_horizon_to_max_steps_ratio: f64,
    /// Dynamic time limit formula (spec 2.5).
    pub time_limit: TimeLimitFormula,
    /// The reference's +16.
    pub time_limit_offset: u32,
    /// Weight of a demo whose t_i = 0 (the reference's 1e-6).
    pub solved_demo_weight: f64,
    /// Stage 1 ends when the solved fraction is strictly greater than this (0.9).
    pub solved_frac_threshold: f64,
    /// Mean of the global history FIFO that advances every demo (`global` method).
    pub global_success_threshold: f64,
    /// Trailing success states kept for resets (light truncation, spec 2.1).
    pub max_trailing_success_states: u32,
}

/// Score function of the forward curriculum (spec 3.3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ForwardScore {
    SuccessOnceScore,
}

/// Rank transforms (spec 3.4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScoreTransform {
    Rankmin,
    Rank,
    Constant,
    Identity,
    Power,
    Softmax,
}

/// How P_S and P_C combine (spec 3.5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LevelMix {
    /// (1 - c) P_S + c P_C, both rank-transformed.
    Reference,
    /// P_S + P_C with the paper's linear staleness, renormalised.
    Paper,
}

/// Stage 2: the seed-based forward curriculum (spec 3). Defaults are the reference's constants.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ForwardConfig {
    /// Score function (spec 3.3).
    pub forward_curriculum: ForwardScore,
    /// Levels are seeds 0..num_seeds-1.
    pub num_seeds: u32,
    /// Transform of the scores into P_S, and its temperature beta_S (spec 3.4, 3.5).
    pub score_transform: ScoreTransform,
    pub score_temperature: f64,
    /// Transform of the staleness counts into P_C, and its temperature beta_C (spec 3.5).
    pub staleness_transform: ScoreTransform,
    pub staleness_temperature: f64,
    /// c, the weight of P_C in the mix (spec 3.5).
    pub staleness_coef: f64,
    /// How P_S and P_C combine (spec 3.5).
    pub mix: LevelMix,
    /// k: the last k returns feed the score.
    pub score_window: u32,
    /// omega: success fraction at or above which a level scores as easy.
    pub score_threshold: f64,
    /// Length of each level's returns FIFO.
    pub returns_buffer_size: u32,
    /// Score of a level before any report.
    pub initial_score: f64,
    /// Add the demos' initial states as levels (deviation 3).
    pub include_demo_starts: bool,
}

/// The service's own options: processes, transport, pacing, persistence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServiceConfig {
    /// Train actor processes; `env.num_envs` is split over them.
    pub num_actors: u32,
    /// Eval actor processes.
    pub num_eval_actors: u32,
    /// `auto` (shm on the learner's host, gRPC elsewhere), `shm` or `grpc`.
    pub transport: Transport,
    /// Seconds after which an unreported lease expires.
    pub lease_timeout_s: f64,
    /// Curriculum snapshot every this many reports (and on shutdown).
    pub snapshot_every_reports: u64,
    /// Curriculum snapshot also when this many seconds have passed since the last one (and there
    /// were reports since).
    pub snapshot_every_s: f64,
    /// An actor that has not called for this many seconds is dropped from the per-actor table
    /// (counted), so the table stays bounded however many actor ids come and go.
    pub forget_actors_after_s: f64,
    /// A stage-1 demo whose frontier has not moved for this many env steps while another demo's
    /// did is flagged as stalled (docs/ALGORITHM.md 2.10); the flag changes nothing in training.
    pub stall_after_env_steps: u64,
    /// Transitions per shared-memory / gRPC batch.
    pub transition_batch: u32,
    /// Warn when an actor's policy lags the learner's by more than this many versions.
    pub max_policy_lag: u64,
    /// Listening ports; 0 = any free port.
    pub curriculum_port: u16,
    pub learner_port: u16,
    pub dashboard_port: u16,
    /// Stop training when the running mean of the last 5 evals reaches this success rate
    /// (`None` = use the whole budget).
    pub stop_at_eval_success: Option<f64>,
    /// `rfcl train` kills and restarts a curriculum server or learner whose process lives but
    /// has not answered for this many seconds (hung, or stopped); `None` = never.
    pub hang_timeout_s: Option<f64>,
}

/// The learner process's own options (not the SAC maths: those are `sac`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LearnerConfig {
    /// CPU threads for the SAC updates; `None` = all cores but one (at least 1), which leaves a
    /// core to the actors and the curriculum server on the same machine.
    pub threads: Option<u32>,
    /// How the SAC updates use those threads on a CPU.
    pub parallelism: Parallelism,
    /// How the critic's gradients are computed on a CPU.
    pub backend: Backend,
}

/// How the learner computes the critic ensemble's loss and gradients on a CPU (CUDA always runs
/// libtorch's autograd). Both compute the same maths (docs/LEARNER.md "Backends").
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// libtorch's ops and autograd.
    Libtorch,
    /// libtorch's matrix products with the LayerNorm, ReLU and bias work between them fused
    /// into one pass per layer forward and backward, and the backward written out: 1.2-1.6x
    /// the critic updates per second of `Libtorch` (benches/RESULTS.md).
    #[default]
    Fused,
}

/// How the learner spreads its SAC updates over `learner.threads` CPU threads.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Parallelism {
    /// The critic ensemble's members are split into one shard per thread, each run with
    /// single-threaded libtorch ops; the threads meet twice per update.
    #[default]
    Members,
    /// One batched computation whose libtorch ops each use every thread (OpenMP); the threads
    /// meet at every op.
    Ops,
}

/// Episodes one evaluation runs over all eval actors: `eval_env.num_envs × eval_steps / horizon`
/// (the reference's eval envs × steps per env, in whole episodes), at least 10 (spec 5.7's
/// smallest count). The horizon is the eval env's, else the training env's.
pub fn episodes_per_eval(cfg: &RunConfig) -> u64 {
    let horizon = cfg
        .eval_env
        .max_episode_steps
        .unwrap_or(cfg.env.max_episode_steps)
        .max(1);
    (u64::from(cfg.eval_env.num_envs) * cfg.sac.eval_steps / u64::from(horizon)).max(10)
}

/// The evaluation point (spec 5.7) a policy published at `env_steps` falls in: the number of
/// multiples of `eval_freq` its env steps passed, or `None` inside the first `num_seed_steps`,
/// where nothing is evaluated. A policy is evaluated when its point is past the last evaluated
/// one's.
pub fn eval_point(env_steps: u64, eval_freq: u64, num_seed_steps: u64) -> Option<u64> {
    (env_steps > num_seed_steps).then(|| env_steps / eval_freq.max(1))
}

impl LearnerConfig {
    /// The learner's thread count: `flag` (`learner --threads`, `rfcl train --learner-threads`)
    /// when given, else `learner.threads`, else `cores - 1`, at least 1.
    pub fn resolve_threads(&self, flag: Option<u32>, cores: usize) -> u32 {
        flag.or(self.threads).unwrap_or_else(|| {
            u32::try_from(cores.saturating_sub(1))
                .unwrap_or(u32::MAX)
                .max(1)
        })
    }

    /// `(libtorch intra-op threads, critic member threads)` for `threads` threads under
    /// `parallelism`.
    pub fn thread_split(&self, threads: u32) -> (u32, u32) {
        let threads = threads.max(1);
        match self.parallelism {
            Parallelism::Members => (1, threads),
            Parallelism::Ops => (threads, 1),
        }
    }

    /// [`resolve_threads`](Self::resolve_threads) with this machine's core count.
    pub fn threads_here(&self, flag: Option<u32>) -> u32 {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        self.resolve_threads(flag, cores)
    }
}

/// How transitions and policy weights travel between actors and the learner.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Transport {
    Auto,
    Shm,
    Grpc,
}

impl Default for RunConfig {
    fn default() -> Self {
        Self {
            name: "run".into(),
            seed: 0,
            demo_seed: None,
            env: EnvConfig::default(),
            eval_env: EvalEnvConfig::default(),
            sac: SacConfig::default(),
            network: NetworkConfig::default(),
            train: TrainConfig::default(),
            reverse: ReverseConfig::default(),
            forward: ForwardConfig::default(),
            service: ServiceConfig::default(),
            learner: LearnerConfig::default(),
        }
    }
}

impl Default for EnvConfig {
    fn default() -> Self {
        Self {
            env_id: "PointMaze-v0".into(),
            suite: Suite::Pointmaze,
            max_episode_steps: 300,
            num_envs: 8,
            control_mode: None,
            env_kwargs: serde_json::Map::new(),
            imports: Vec::new(),
            success: None,
            obs_dim: None,
            action_dim: None,
        }
    }
}

impl Default for EvalEnvConfig {
    fn default() -> Self {
        Self {
            num_envs: 2,
            max_episode_steps: None,
            seed_offset: 1_000_000,
            video_every: 0,
            video_size: 256,
        }
    }
}

impl Default for SacConfig {
    /// The wall-time-efficient ("fast") set of spec 8.2 with the shared values of 8.1.
    fn default() -> Self {
        Self {
            num_seed_steps: 5000,
            replay_buffer_capacity: 1_000_000,
            batch_size: 256,
            steps_per_env: 4,
            grad_updates_per_step: 16,
            actor_update_freq: 1,
            critic_ensemble: 10,
            target_pool: 10,
            num_min_qs: 2,
            discount: 0.99,
            tau: 0.005,
            backup_entropy: false,
            learnable_temp: true,
            initial_temperature: 1.0,
            target_entropy: None,
            actor_lr: 3e-4,
            critic_lr: 3e-4,
            temp_lr: 3e-4,
            adam_beta1: 0.9,
            adam_beta2: 0.999,
            adam_eps: 1e-8,
            eval_freq: 50_000,
            eval_steps: 1000,
            log_freq: 1000,
            save_freq: 50_000,
            save_every_s: 60.0,
            utd_mode: UtdMode::Sync,
            device: Device::Cpu,
            matmul_precision: MatmulPrecision::Fp32,
        }
    }
}

impl Default for NetworkConfig {
    fn default() -> Self {
        Self {
            actor_features: vec![256, 256, 256],
            critic_features: vec![256, 256, 256],
            critic_layer_norm: true,
            layer_norm_eps: 1e-6,
            log_std_min: -5.0,
            log_std_max: 2.0,
        }
    }
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            steps: 2_000_000,
            dataset_path: None,
            num_demos: 5,
            shuffle_demos: true,
            data_action_scale: None,
            train_on_demo_actions: true,
            load_actor: true,
            load_critic: true,
            load_as_offline_buffer: true,
            load_as_online_buffer: false,
            use_orig_env_for_eval: true,
            eval_start_of_demos: false,
            mode: TrainMode::Rfcl,
            stage_2_only: false,
            stage_1_only: false,
        }
    }
}

impl Default for ReverseConfig {
    fn default() -> Self {
        Self {
            curriculum_method: CurriculumMethod::PerDemo,
            start_step_sampler: StartStepSampler::Geometric,
            geometric_probs: vec![0.5, 0.25, 0.125, 0.0625, 0.0625],
            reverse_step_size: 4,
            per_demo_buffer_size: 3,
            demo_horizon_to_max_steps_ratio: 3.0,
            time_limit: TimeLimitFormula::Reference,
            time_limit_offset: 16,
            solved_demo_weight: 1e-6,
            solved_frac_threshold: 0.9,
            global_success_threshold: 0.9,
            max_trailing_success_states: 50,
        }
    }
}

impl Default for ForwardConfig {
    fn default() -> Self {
        Self {
            forward_curriculum: ForwardScore::SuccessOnceScore,
            num_seeds: 1000,
            score_transform: ScoreTransform::Rankmin,
            score_temperature: 0.1,
            staleness_transform: ScoreTransform::Rankmin,
            staleness_temperature: 0.1,
            staleness_coef: 0.1,
            mix: LevelMix::Reference,
            score_window: 5,
            score_threshold: 0.75,
            returns_buffer_size: 20,
            initial_score: 2.0,
            include_demo_starts: true,
        }
    }
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self {
            num_actors: 2,
            num_eval_actors: 1,
            transport: Transport::Auto,
            lease_timeout_s: 120.0,
            snapshot_every_reports: 500,
            snapshot_every_s: 15.0,
            forget_actors_after_s: 600.0,
            stall_after_env_steps: 50_000,
            transition_batch: 64,
            max_policy_lag: 50,
            curriculum_port: 0,
            learner_port: 0,
            dashboard_port: 0,
            stop_at_eval_success: None,
            hang_timeout_s: Some(60.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn learner_threads_resolve_flag_then_config_then_all_cores_but_one() {
        let default = LearnerConfig::default();
        assert_eq!(default.resolve_threads(None, 2), 1);
        assert_eq!(default.resolve_threads(None, 16), 15);
        assert_eq!(default.resolve_threads(None, 1), 1);
        assert_eq!(default.resolve_threads(None, 0), 1);
        let set = LearnerConfig {
            threads: Some(4),
            ..LearnerConfig::default()
        };
        assert_eq!(set.resolve_threads(None, 2), 4);
        assert_eq!(set.resolve_threads(Some(3), 2), 3);
        assert_eq!(default.resolve_threads(Some(2), 16), 2);
        assert!(default.threads_here(None) >= 1);
    }

    #[test]
    fn learner_parallelism_splits_threads_between_members_and_ops() {
        let members = LearnerConfig::default();
        assert_eq!(members.parallelism, Parallelism::Members);
        assert_eq!(members.thread_split(2), (1, 2));
        assert_eq!(members.thread_split(0), (1, 1));
        let ops = LearnerConfig {
            parallelism: Parallelism::Ops,
            ..LearnerConfig::default()
        };
        assert_eq!(ops.thread_split(3), (3, 1));
    }

    /// Every 20,000 env steps past 5,000 seed steps: 4,999 and 5,000 are seed steps; 19,999 is in
    /// point 0 (nothing passed), 20,000 and 39,999 in point 1, 40,000 in point 2.
    #[test]
    fn eval_points_count_the_multiples_passed_after_the_seed_steps() {
        let point = |steps| eval_point(steps, 20_000, 5_000);
        assert_eq!(point(4_999), None);
        assert_eq!(point(5_000), None);
        assert_eq!(point(19_999), Some(0));
        assert_eq!(point(20_000), Some(1));
        assert_eq!(point(39_999), Some(1));
        assert_eq!(point(40_000), Some(2));
        // A seed phase longer than the period: the first point after it is the multiples passed.
        assert_eq!(eval_point(30_000, 20_000, 30_000), None);
        assert_eq!(eval_point(30_001, 20_000, 30_000), Some(1));
        assert_eq!(
            eval_point(7, 0, 0),
            Some(7),
            "a zero period counts every step"
        );
    }
}
