//! Rollouts: the pure core of an actor. A [`Rollout`] steps K envs ([`Env`] trait objects) from
//! reset leases with a policy and produces transition records and episode reports; it does no I/O,
//! so the actor's transport shell and `rfcl eval` share it, and tests drive it directly.
//!
//! Per episode (one lease):
//! * **Reset** (spec 2.4, 12.13): a DEMO_STATE lease, and a LEVEL lease that names a demo's start
//!   (it carries the demo's state), reset with the lease's seed and options first and then set the
//!   demo state; other leases reset from the seed (and options) alone.
//! * **Actions**: uniform in `[-1, 1]^A` during stage 1's seed steps or before any policy arrived
//!   (spec 5.4, [`explores_uniformly`]), else the policy: stochastic for training, deterministic
//!   tanh(μ) for evaluation (spec 5.7). Both are agent actions; with an action scale
//!   ([`Rollout::with_action_scale`], `train.data_action_scale`) the env gets [`env_action`]'s
//!   clip(a / s, −1, 1) while the transition keeps the agent action a (spec 6.4).
//! * **Reward** `+1` on every step whose resulting state is a success state; episodes never end
//!   on success and `mask` is always 1 (spec 5.6, 12.6).
//! * **Truncation** after the lease's `time_limit` steps (the stage-1 dynamic limit capped by the
//!   horizon, spec 2.5); the last transition's `next_obs` is the true final observation (spec 5.5).
//! * **Report**: success at the final step, success at any step, return, length, the policy
//!   version (and its learner env steps) that acted last, the lease's stage epoch and the actor's
//!   env steps so far (the heartbeat).
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rfcl_core::lease::{shorten_reason, EpisodeReport, LeaseKind, ResetLease};
use rfcl_core::transition::Transition;

use crate::env::{Env, EnvError, Frame};
use crate::policy::{explores_uniformly, uniform_action, PolicyHandle};

/// Why a rollout could not go on: the env refused a lease's reset or an action. Both mean the
/// lease and the env disagree (a wrong env for the run, a corrupt demo state), never a transient
/// condition.
#[derive(Debug, thiserror::Error)]
pub enum RolloutError {
    #[error("env {env}: lease {lease_id} ({kind:?}) could not reset the env: {error}")]
    Reset {
        env: usize,
        lease_id: u64,
        kind: LeaseKind,
        /// The lease's, for its report ([`Rollout::reset_failure_report`]).
        stage_epoch: u64,
        error: EnvError,
    },
    #[error("env {env}: step {step} of lease {lease_id} failed: {error}")]
    Step {
        env: usize,
        lease_id: u64,
        step: u32,
        error: EnvError,
    },
    #[error("env {env} already runs lease {running}; it cannot begin lease {offered}")]
    Busy {
        env: usize,
        running: u64,
        offered: u64,
    },
    #[error("there is no env {env} (this rollout has {envs})")]
    NoSuchEnv { env: usize, envs: usize },
    #[error("the policy returned {got} action components, the env takes {expected}")]
    PolicyActionDim { expected: usize, got: usize },
    #[error("the action scale (docs/ALGORITHM.md 6.4) does not fit env {env}: {problem}")]
    ActionScale { env: usize, problem: String },
    #[error("env {env} could not render: {error}")]
    Render { env: usize, error: EnvError },
}

/// Spec 6.4 (`train.data_action_scale`): the env action for agent action `a` under the
/// per-dimension scale `s`. The reference wraps the env in RescaleAction to [−s, s] plus
/// ClipAction, so agent action a maps to env action a / s, clipped to the env's [−1, 1]:
/// `env_d = clip(a_d / s_d, −1, 1)`. Transitions keep `a` (the learner trains in agent units, as
/// it does with the rescaled demo actions). `scale` has one value > 0 per action dimension.
pub fn env_action(action: &[f32], scale: &[f32]) -> Vec<f32> {
    debug_assert_eq!(action.len(), scale.len());
    action
        .iter()
        .zip(scale)
        .map(|(a, s)| (a / s).clamp(-1.0, 1.0))
        .collect()
}

/// Seed of env `env_index` of actor `actor_id` in a run seeded `run_seed`, so a run can be reproduced: the three go through SplitMix64 one after the other, so neighbouring ids
/// get unrelated streams. The env's own RNG and the env's action RNG both derive from it.
pub fn derive_seed(run_seed: u64, actor_id: u32, env_index: u32) -> u64 {
    let mut x = splitmix64(run_seed ^ 0x5246_434c_0000_0000); // "RFCL"
    x = splitmix64(x ^ u64::from(actor_id));
    splitmix64(x ^ (u64::from(env_index) << 32))
}

fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// How a rollout acts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RolloutSettings {
    /// Written into every transition and report.
    pub actor_id: u32,
    /// Stage-1 uniform-exploration threshold (spec 5.4).
    pub num_seed_steps: u64,
    /// Deterministic actions tanh(μ) (evaluation, spec 5.7); stochastic otherwise.
    pub deterministic: bool,
}

/// One episode in progress.
#[derive(Debug, Clone)]
struct Episode {
    lease: ResetLease,
    obs: Vec<f32>,
    length: u32,
    episode_return: f64,
    success_once: bool,
    success: bool,
    policy_version: u64,
    policy_env_steps: u64,
}

struct Slot {
    env: Box<dyn Env>,
    rng: ChaCha8Rng,
    episode: Option<Episode>,
}

/// What one [`Rollout::step`] produced. Reused between steps (cleared by the caller).
#[derive(Debug, Default)]
pub struct StepOutput {
    /// One transition per env that stepped, in env order.
    pub transitions: Vec<Transition>,
    /// Episodes that reached their time limit on this step, with the env index.
    pub finished: Vec<(usize, EpisodeReport)>,
}

impl StepOutput {
    pub fn clear(&mut self) {
        self.transitions.clear();
        self.finished.clear();
    }
}

/// K envs stepped in lockstep from leases, with the latest policy.
pub struct Rollout {
    settings: RolloutSettings,
    /// Spec 6.4's s, when the run rescales actions ([`env_action`]).
    action_scale: Option<Vec<f32>>,
    slots: Vec<Slot>,
    env_steps: u64,
    episodes: u64,
    abandoned: u64,
    reset_failures_in_a_row: u32,
}

impl Rollout {
    /// `envs[i]` gets the action RNG of `derive_seed(run_seed, actor_id, i)`.
    pub fn new(envs: Vec<Box<dyn Env>>, run_seed: u64, settings: RolloutSettings) -> Self {
        let slots = envs
            .into_iter()
            .enumerate()
            .map(|(i, env)| Slot {
                env,
                rng: ChaCha8Rng::seed_from_u64(derive_seed(run_seed, settings.actor_id, i as u32)),
                episode: None,
            })
            .collect();
        Rollout {
            settings,
            action_scale: None,
            slots,
            env_steps: 0,
            episodes: 0,
            abandoned: 0,
            reset_failures_in_a_row: 0,
        }
    }

    pub fn settings(&self) -> RolloutSettings {
        self.settings
    }

    /// Steps the envs with spec 6.4's action scale s (`train.data_action_scale`; `None`: the env
    /// gets the agent action as it is): the env gets [`env_action`], transitions keep the agent
    /// action. `scale` needs one finite value > 0 per action dimension of every env.
    pub fn with_action_scale(mut self, scale: Option<Vec<f32>>) -> Result<Self, RolloutError> {
        if let Some(s) = &scale {
            for (env, slot) in self.slots.iter().enumerate() {
                let problem = if s.len() != slot.env.action_dim() {
                    format!(
                        "{} values for {} action dimensions",
                        s.len(),
                        slot.env.action_dim()
                    )
                } else if let Some(bad) = s.iter().find(|v| !(v.is_finite() && **v > 0.0)) {
                    format!("{bad} is not a finite value > 0")
                } else {
                    continue;
                };
                return Err(RolloutError::ActionScale { env, problem });
            }
        }
        self.action_scale = scale;
        Ok(self)
    }

    /// Spec 6.4's s this rollout steps its envs with, if any.
    pub fn action_scale(&self) -> Option<&[f32]> {
        self.action_scale.as_deref()
    }

    pub fn num_envs(&self) -> usize {
        self.slots.len()
    }

    /// Env steps taken by this rollout, over all envs (the reports' `actor_env_steps` continue
    /// from [`Rollout::set_env_steps`]).
    pub fn env_steps(&self) -> u64 {
        self.env_steps
    }

    /// Continues the env-step count (a respawned actor takes up its predecessor's count).
    pub fn set_env_steps(&mut self, steps: u64) {
        self.env_steps = steps;
    }

    /// Simulator worker restarts of this rollout's envs so far ([`Env::restarts`]): the reports'
    /// `sim_restarts`.
    pub fn sim_restarts(&self) -> u64 {
        self.slots.iter().map(|s| s.env.restarts()).sum()
    }

    /// Episodes finished.
    pub fn episodes(&self) -> u64 {
        self.episodes
    }

    /// Resets that failed since the last one that worked, over all envs: one bad demo state
    /// fails once, an env that cannot reset at all fails every time.
    pub fn reset_failures_in_a_row(&self) -> u32 {
        self.reset_failures_in_a_row
    }

    /// The report of a lease whose reset failed ([`RolloutError::Reset`]): no episode ran, so it
    /// has no steps and no success, and carries the reason (shortened to the wire's bound).
    pub fn reset_failure_report(
        &self,
        lease_id: u64,
        stage_epoch: u64,
        error: &EnvError,
    ) -> EpisodeReport {
        EpisodeReport {
            lease_id,
            success_at_end: false,
            success_once: false,
            episode_return: 0.0,
            length: 0,
            policy_version: 0,
            stage_epoch,
            actor_id: self.settings.actor_id,
            actor_env_steps: self.env_steps,
            policy_env_steps: 0,
            sim_restarts: self.sim_restarts(),
            reset_failure: Some(shorten_reason(&error.to_string())),
        }
    }

    /// Episodes dropped unfinished by [`Rollout::abandon_epochs_before`].
    pub fn abandoned(&self) -> u64 {
        self.abandoned
    }

    /// Envs without an episode: each needs a lease.
    pub fn idle_envs(&self) -> Vec<usize> {
        (0..self.slots.len())
            .filter(|&i| self.slots[i].episode.is_none())
            .collect()
    }

    /// Env `env`'s current state as an image (an eval video's frame): after [`Rollout::begin`],
    /// the reset state; after a step that finished its episode, that episode's last state.
    pub fn render(&mut self, env: usize) -> Result<Frame, RolloutError> {
        let envs = self.slots.len();
        let slot = self
            .slots
            .get_mut(env)
            .ok_or(RolloutError::NoSuchEnv { env, envs })?;
        slot.env
            .render()
            .map_err(|error| RolloutError::Render { env, error })
    }

    /// Envs running an episode.
    pub fn active_envs(&self) -> usize {
        self.slots.iter().filter(|s| s.episode.is_some()).count()
    }

    /// The lease env `env` runs, if any.
    pub fn lease(&self, env: usize) -> Option<&ResetLease> {
        self.slots
            .get(env)
            .and_then(|s| s.episode.as_ref().map(|e| &e.lease))
    }

    /// Starts an episode of `lease` in env `env` (spec 2.4): reset with the lease's seed and options,
    /// then, when the lease carries an env state (DEMO_STATE, or a LEVEL at a demo's start), set it.
    pub fn begin(&mut self, env: usize, lease: ResetLease) -> Result<(), RolloutError> {
        let envs = self.slots.len();
        let slot = self
            .slots
            .get_mut(env)
            .ok_or(RolloutError::NoSuchEnv { env, envs })?;
        if let Some(running) = &slot.episode {
            return Err(RolloutError::Busy {
                env,
                running: running.lease.lease_id,
                offered: lease.lease_id,
            });
        }
        let reset = if lease.env_state.is_empty() {
            slot.env
                .reset_to_seed(lease.reset.seed, &lease.reset.options)
        } else {
            slot.env
                .reset_to_state(lease.reset.seed, &lease.reset.options, &lease.env_state)
        };
        let obs = match reset {
            Ok(obs) => obs,
            Err(error) => {
                self.reset_failures_in_a_row += 1;
                return Err(RolloutError::Reset {
                    env,
                    lease_id: lease.lease_id,
                    kind: lease.kind,
                    stage_epoch: lease.stage_epoch,
                    error,
                });
            }
        };
        self.reset_failures_in_a_row = 0;
        slot.episode = Some(Episode {
            lease,
            obs,
            length: 0,
            episode_return: 0.0,
            success_once: false,
            success: false,
            policy_version: 0,
            policy_env_steps: 0,
        });
        Ok(())
    }

    /// Steps every env that runs an episode once, with `policy` (or uniform actions, spec 5.4),
    /// appending a transition per env and a report per episode that reached its time limit.
    /// Finished envs become idle.
    pub fn step(
        &mut self,
        mut policy: Option<&mut PolicyHandle>,
        out: &mut StepOutput,
    ) -> Result<(), RolloutError> {
        let settings = self.settings;
        let first_finished = out.finished.len();
        for (index, slot) in self.slots.iter_mut().enumerate() {
            let Some(episode) = slot.episode.as_mut() else {
                continue;
            };
            let action_dim = slot.env.action_dim();
            let uniform = explores_uniformly(
                episode.lease.stage,
                policy.as_ref().map(|p| p.env_steps),
                settings.num_seed_steps,
            ) && !settings.deterministic;
            let (action, version, policy_steps) = match policy.as_deref_mut() {
                Some(p) if !uniform => {
                    let action = p
                        .policy
                        .act(&episode.obs, settings.deterministic, &mut slot.rng);
                    (action, p.version, p.env_steps)
                }
                held => (
                    uniform_action(action_dim, &mut slot.rng),
                    held.as_ref().map_or(0, |p| p.version),
                    held.as_ref().map_or(0, |p| p.env_steps),
                ),
            };
            if action.len() != action_dim {
                return Err(RolloutError::PolicyActionDim {
                    expected: action_dim,
                    got: action.len(),
                });
            }
            let scaled;
            let env_act = match self.action_scale.as_deref() {
                Some(scale) => {
                    scaled = env_action(&action, scale);
                    &scaled
                }
                None => &action,
            };
            let outcome = slot.env.step(env_act).map_err(|error| RolloutError::Step {
                env: index,
                lease_id: episode.lease.lease_id,
                step: episode.length,
                error,
            })?;
            let reward = if outcome.success { 1.0f32 } else { 0.0 };
            episode.length += 1;
            episode.episode_return += f64::from(reward);
            episode.success_once |= outcome.success;
            episode.success = outcome.success;
            episode.policy_version = version;
            episode.policy_env_steps = policy_steps;
            self.env_steps += 1;
            let obs = std::mem::replace(&mut episode.obs, outcome.obs.clone());
            out.transitions.push(Transition {
                obs,
                action,
                reward,
                next_obs: outcome.obs,
                mask: 1.0,
                stage_epoch: episode.lease.stage_epoch,
                actor_id: settings.actor_id,
                policy_version: version,
            });
            if episode.length >= episode.lease.time_limit {
                let done = slot.episode.take().expect("checked above");
                self.episodes += 1;
                out.finished.push((
                    index,
                    EpisodeReport {
                        lease_id: done.lease.lease_id,
                        success_at_end: done.success,
                        success_once: done.success_once,
                        episode_return: done.episode_return,
                        length: done.length,
                        policy_version: done.policy_version,
                        stage_epoch: done.lease.stage_epoch,
                        actor_id: settings.actor_id,
                        actor_env_steps: self.env_steps,
                        policy_env_steps: done.policy_env_steps,
                        // Stamped below, once every env has stepped (a restart may happen in any).
                        sim_restarts: 0,
                        reset_failure: None,
                    },
                ));
            }
        }
        let sim_restarts = self.sim_restarts();
        for (_, report) in &mut out.finished[first_finished..] {
            report.sim_restarts = sim_restarts;
        }
        Ok(())
    }

    /// Drops the unfinished episodes of leases from stage epochs before `epoch`: the curriculum
    /// server would refuse their reports and the learner drops their transitions (spec 4), so
    /// finishing them only wastes steps. Their envs become idle. Returns how many were dropped.
    pub fn abandon_epochs_before(&mut self, epoch: u64) -> usize {
        let mut dropped = 0;
        for slot in &mut self.slots {
            if slot
                .episode
                .as_ref()
                .is_some_and(|e| e.lease.stage_epoch < epoch)
            {
                slot.episode = None;
                dropped += 1;
            }
        }
        self.abandoned += dropped as u64;
        dropped
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::Policy;
    use rfcl_core::lease::ResetArgs;

    /// A 1-D env: the state is a position, an action adds to it, success is position >= 3.
    struct Line {
        pos: f32,
        layout: crate::env::StateLayout,
        resets: Vec<(Option<u64>, Option<Vec<f32>>)>,
        /// Worker restarts so far; [`Line::restarting`] counts one on every step, as a Python
        /// env whose worker keeps crashing would.
        restarts: u64,
        restarts_per_step: u64,
    }

    impl Line {
        fn boxed() -> Box<dyn Env> {
            Self::with_restarts_per_step(0)
        }

        fn restarting() -> Box<dyn Env> {
            Self::with_restarts_per_step(1)
        }

        fn with_restarts_per_step(restarts_per_step: u64) -> Box<dyn Env> {
            Box::new(Line {
                pos: 0.0,
                layout: crate::env::StateLayout::flat(1),
                resets: Vec::new(),
                restarts: 0,
                restarts_per_step,
            })
        }
    }

    impl Env for Line {
        fn obs_dim(&self) -> usize {
            1
        }
        fn action_dim(&self) -> usize {
            1
        }
        fn horizon(&self) -> usize {
            100
        }
        fn state_layout(&self) -> &crate::env::StateLayout {
            &self.layout
        }
        fn reset_to_seed(
            &mut self,
            seed: Option<u64>,
            _: &serde_json::Value,
        ) -> Result<Vec<f32>, EnvError> {
            self.resets.push((seed, None));
            self.pos = seed.unwrap_or(0) as f32 / 10.0;
            Ok(vec![self.pos])
        }
        fn reset_to_state(
            &mut self,
            seed: Option<u64>,
            _: &serde_json::Value,
            state: &[f32],
        ) -> Result<Vec<f32>, EnvError> {
            if state.len() != 1 {
                return Err(EnvError::StateLen {
                    expected: 1,
                    got: state.len(),
                });
            }
            self.resets.push((seed, Some(state.to_vec())));
            self.pos = state[0];
            Ok(vec![self.pos])
        }
        fn step(&mut self, action: &[f32]) -> Result<crate::env::StepOutcome, EnvError> {
            self.pos += action[0];
            self.restarts += self.restarts_per_step;
            Ok(crate::env::StepOutcome {
                obs: vec![self.pos],
                success: self.pos >= 3.0,
            })
        }
        fn get_state(&self) -> Vec<f32> {
            vec![self.pos]
        }
        fn restarts(&self) -> u64 {
            self.restarts
        }
    }

    /// Always +1 (stochastic) or +0.5 (deterministic).
    struct Push;
    impl Policy for Push {
        fn act(&mut self, _: &[f32], deterministic: bool, _: &mut ChaCha8Rng) -> Vec<f32> {
            vec![if deterministic { 0.5 } else { 1.0 }]
        }
        fn load(&mut self, _: &[u8]) -> Result<(), crate::policy::LoadError> {
            Ok(())
        }
    }

    fn lease(id: u64, kind: LeaseKind, state: Vec<f32>, time_limit: u32, stage: u32) -> ResetLease {
        ResetLease {
            lease_id: id,
            kind,
            demo_id: 0,
            start_index: 0,
            env_state: state,
            reset: ResetArgs {
                seed: Some(20),
                options: serde_json::json!({}),
            },
            time_limit,
            stage,
            stage_epoch: stage as u64 - 1,
            level: 0,
        }
    }

    fn settings(deterministic: bool) -> RolloutSettings {
        RolloutSettings {
            actor_id: 7,
            num_seed_steps: 100,
            deterministic,
        }
    }

    fn handle(version: u64, env_steps: u64) -> PolicyHandle {
        PolicyHandle {
            version,
            env_steps,
            policy: Box::new(Push),
        }
    }

    #[test]
    fn an_episode_yields_transitions_with_sparse_reward_and_one_report() {
        let mut r = Rollout::new(vec![Line::boxed()], 1, settings(false));
        r.begin(0, lease(5, LeaseKind::DemoState, vec![1.0], 4, 1))
            .unwrap();
        let mut policy = handle(3, 500);
        let mut out = StepOutput::default();
        for _ in 0..4 {
            r.step(Some(&mut policy), &mut out).unwrap();
        }
        // Positions 2, 3, 4, 5 after each step: success from the second step on, never ended.
        let rewards: Vec<f32> = out.transitions.iter().map(|t| t.reward).collect();
        assert_eq!(rewards, [0.0, 1.0, 1.0, 1.0]);
        assert!(out.transitions.iter().all(|t| t.mask == 1.0
            && t.actor_id == 7
            && t.policy_version == 3
            && t.stage_epoch == 0));
        // obs chain: each next_obs is the following obs; the last next_obs is the final obs.
        for w in out.transitions.windows(2) {
            assert_eq!(w[0].next_obs, w[1].obs);
        }
        assert_eq!(out.transitions[0].obs, [1.0]);
        assert_eq!(out.transitions[3].next_obs, [5.0]);
        assert_eq!(out.finished.len(), 1);
        let (env, report) = &out.finished[0];
        assert_eq!(*env, 0);
        assert_eq!(
            *report,
            EpisodeReport {
                lease_id: 5,
                success_at_end: true,
                success_once: true,
                episode_return: 3.0,
                length: 4,
                policy_version: 3,
                stage_epoch: 0,
                actor_id: 7,
                actor_env_steps: 4,
                policy_env_steps: 500,
                sim_restarts: 0,
                reset_failure: None,
            }
        );
        assert_eq!(r.idle_envs(), [0]);
        assert_eq!((r.env_steps(), r.episodes()), (4, 1));
    }

    #[test]
    fn demo_state_leases_reset_with_the_seed_first_then_the_state() {
        let mut r = Rollout::new(vec![Line::boxed()], 1, settings(false));
        r.begin(0, lease(1, LeaseKind::DemoState, vec![2.5], 1, 1))
            .unwrap();
        let mut out = StepOutput::default();
        r.step(None, &mut out).unwrap();
        assert_eq!(out.transitions[0].obs, [2.5]);
        // A seed-only lease starts where the seed puts it (Line: seed / 10).
        r.begin(0, lease(2, LeaseKind::Eval, vec![], 1, 1)).unwrap();
        out.clear();
        r.step(None, &mut out).unwrap();
        assert_eq!(out.transitions[0].obs, [2.0]);
    }

    #[test]
    fn a_refused_state_names_the_lease() {
        let mut r = Rollout::new(vec![Line::boxed()], 1, settings(false));
        let err = r
            .begin(0, lease(9, LeaseKind::DemoState, vec![1.0, 2.0], 5, 1))
            .unwrap_err();
        assert!(
            matches!(err, RolloutError::Reset { lease_id: 9, .. }),
            "{err}"
        );
        assert!(err.to_string().contains("lease 9"), "{err}");
        assert_eq!(r.reset_failures_in_a_row(), 1);
        // Its report: no episode, the reason, the lease's epoch.
        let RolloutError::Reset {
            lease_id,
            stage_epoch,
            error,
            ..
        } = &err
        else {
            unreachable!()
        };
        let report = r.reset_failure_report(*lease_id, *stage_epoch, error);
        assert_eq!((report.lease_id, report.length, report.actor_id), (9, 0, 7));
        assert!(!report.success_once && report.episode_return == 0.0);
        assert_eq!(
            report.reset_failure.as_deref(),
            Some("state has 2 values, the env's state layout has 1")
        );
        assert!(r
            .begin(0, lease(8, LeaseKind::DemoState, vec![], 5, 1))
            .is_ok_and(|()| r.reset_failures_in_a_row() == 0));
        r.abandon_epochs_before(u64::MAX);
        // The env stays idle and takes a good lease.
        assert_eq!(r.idle_envs(), [0]);
        r.begin(0, lease(10, LeaseKind::DemoState, vec![1.0], 5, 1))
            .unwrap();
        let busy = r
            .begin(0, lease(11, LeaseKind::DemoState, vec![1.0], 5, 1))
            .unwrap_err();
        assert!(matches!(
            busy,
            RolloutError::Busy {
                running: 10,
                offered: 11,
                ..
            }
        ));
    }

    #[test]
    fn uniform_actions_until_the_seed_steps_then_the_policy() {
        let mut r = Rollout::new(vec![Line::boxed(), Line::boxed()], 1, settings(false));
        r.begin(0, lease(1, LeaseKind::DemoState, vec![0.0], 50, 1))
            .unwrap();
        r.begin(1, lease(2, LeaseKind::Level, vec![], 50, 2))
            .unwrap();
        let mut out = StepOutput::default();
        // No policy: both envs act uniformly and record version 0.
        r.step(None, &mut out).unwrap();
        assert!(out.transitions.iter().all(|t| t.policy_version == 0
            && t.action[0] != 1.0
            && (-1.0..=1.0).contains(&t.action[0])));
        // A policy below the seed steps: stage 1 still uniform, stage 2 follows the policy.
        out.clear();
        let mut early = handle(1, 99);
        r.step(Some(&mut early), &mut out).unwrap();
        assert_ne!(out.transitions[0].action, [1.0]);
        assert_eq!(out.transitions[0].policy_version, 1);
        assert_eq!(out.transitions[1].action, [1.0]);
        // Past the seed steps the policy acts in stage 1 too.
        out.clear();
        let mut trained = handle(2, 100);
        r.step(Some(&mut trained), &mut out).unwrap();
        assert!(out.transitions.iter().all(|t| t.action == [1.0]));
    }

    #[test]
    fn evaluation_is_deterministic_from_the_first_step() {
        let mut r = Rollout::new(vec![Line::boxed()], 1, settings(true));
        r.begin(0, lease(1, LeaseKind::Eval, vec![], 3, 1)).unwrap();
        let mut out = StepOutput::default();
        let mut p = handle(4, 0);
        for _ in 0..3 {
            r.step(Some(&mut p), &mut out).unwrap();
        }
        assert!(out.transitions.iter().all(|t| t.action == [0.5]));
        let report = &out.finished[0].1;
        assert_eq!((report.policy_version, report.length), (4, 3));
        // Start 2.0, then 2.5, 3.0, 3.5: success on the last two steps.
        assert_eq!(report.episode_return, 2.0);
    }

    #[test]
    fn success_once_without_success_at_end() {
        struct Back(u32);
        impl Policy for Back {
            fn act(&mut self, _: &[f32], _: bool, _: &mut ChaCha8Rng) -> Vec<f32> {
                self.0 += 1;
                vec![if self.0 == 1 { 1.0 } else { -1.0 }]
            }
            fn load(&mut self, _: &[u8]) -> Result<(), crate::policy::LoadError> {
                Ok(())
            }
        }
        let mut r = Rollout::new(vec![Line::boxed()], 1, settings(false));
        r.begin(0, lease(1, LeaseKind::DemoState, vec![2.5], 3, 1))
            .unwrap();
        let mut p = PolicyHandle {
            version: 1,
            env_steps: 1000,
            policy: Box::new(Back(0)),
        };
        let mut out = StepOutput::default();
        for _ in 0..3 {
            r.step(Some(&mut p), &mut out).unwrap();
        }
        let report = &out.finished[0].1;
        assert!(report.success_once && !report.success_at_end);
        assert_eq!(report.episode_return, 1.0);
    }

    /// A [`Line`] env and `second` on episodes of 2 and 3 steps, after two steps: env 0's
    /// episode has just finished, env 1's has a step to go.
    fn two_episodes_two_steps_in(second: Box<dyn Env>) -> (Rollout, StepOutput) {
        let mut r = Rollout::new(vec![Line::boxed(), second], 1, settings(false));
        r.begin(0, lease(1, LeaseKind::DemoState, vec![0.0], 2, 1))
            .unwrap();
        r.begin(1, lease(2, LeaseKind::DemoState, vec![0.0], 3, 1))
            .unwrap();
        let mut out = StepOutput::default();
        r.step(None, &mut out).unwrap();
        r.step(None, &mut out).unwrap();
        (r, out)
    }

    #[test]
    fn envs_finish_independently_and_heartbeat_counts_all_envs() {
        let (mut r, mut out) = two_episodes_two_steps_in(Line::boxed());
        assert_eq!(out.finished.len(), 1);
        assert_eq!(out.finished[0].0, 0);
        // The heartbeat counts the steps taken so far: env 0's second step is the third.
        assert_eq!(out.finished[0].1.actor_env_steps, 3);
        assert_eq!(r.idle_envs(), [0]);
        // An idle env does not step.
        out.clear();
        r.step(None, &mut out).unwrap();
        assert_eq!(out.transitions.len(), 1);
        assert_eq!(out.finished[0].1.actor_env_steps, 5);
        assert_eq!(r.active_envs(), 0);
    }

    #[test]
    fn reports_carry_the_worker_restarts_of_all_envs() {
        let (mut r, mut out) = two_episodes_two_steps_in(Line::restarting());
        // Env 0 never restarts; its report counts env 1's restarts, including the one of the
        // step in which env 0 finished.
        assert_eq!(out.finished[0].1.sim_restarts, 2);
        out.clear();
        r.step(None, &mut out).unwrap();
        assert_eq!(out.finished[0].1.sim_restarts, 3);
        assert_eq!(r.sim_restarts(), 3);
    }

    #[test]
    fn a_new_stage_epoch_abandons_older_episodes() {
        let mut r = Rollout::new(vec![Line::boxed(), Line::boxed()], 1, settings(false));
        r.begin(0, lease(1, LeaseKind::DemoState, vec![0.0], 20, 1))
            .unwrap();
        r.begin(1, lease(2, LeaseKind::Level, vec![], 20, 2))
            .unwrap();
        assert_eq!(r.abandon_epochs_before(1), 1);
        assert_eq!(r.idle_envs(), [0]);
        assert_eq!(r.lease(1).unwrap().lease_id, 2);
        assert_eq!(r.abandoned(), 1);
    }

    #[test]
    fn a_wrong_sized_action_is_an_error() {
        struct Wide;
        impl Policy for Wide {
            fn act(&mut self, _: &[f32], _: bool, _: &mut ChaCha8Rng) -> Vec<f32> {
                vec![0.0, 0.0]
            }
            fn load(&mut self, _: &[u8]) -> Result<(), crate::policy::LoadError> {
                Ok(())
            }
        }
        let mut r = Rollout::new(vec![Line::boxed()], 1, settings(true));
        r.begin(0, lease(1, LeaseKind::Eval, vec![], 3, 1)).unwrap();
        let mut p = PolicyHandle {
            version: 1,
            env_steps: 0,
            policy: Box::new(Wide),
        };
        let err = r
            .step(Some(&mut p), &mut StepOutput::default())
            .unwrap_err();
        assert!(matches!(
            err,
            RolloutError::PolicyActionDim {
                expected: 1,
                got: 2
            }
        ));
    }

    /// Spec 6.4 on a hand-computed case: env_d = clip(a_d / s_d, -1, 1).
    #[test]
    fn env_actions_are_agent_actions_over_the_scale_clipped() {
        let agent = [0.2f32, -0.9, 0.9, -0.6];
        let scale = [0.5f32, 2.0, 0.8, 0.5];
        // 0.2 / 0.5 = 0.4; -0.9 / 2 = -0.45; 0.9 / 0.8 = 1.125 -> 1; -0.6 / 0.5 = -1.2 -> -1.
        assert_eq!(env_action(&agent, &scale), [0.4, -0.45, 1.0, -1.0]);
        assert_eq!(env_action(&agent, &[1.0; 4]), agent);
    }

    #[test]
    fn a_scaled_rollout_steps_the_env_with_a_over_s_and_records_a() {
        let mut r = Rollout::new(vec![Line::boxed()], 1, settings(false))
            .with_action_scale(Some(vec![2.0]))
            .unwrap();
        r.begin(0, lease(1, LeaseKind::DemoState, vec![1.0], 4, 1))
            .unwrap();
        let mut policy = handle(3, 500);
        let mut out = StepOutput::default();
        for _ in 0..4 {
            r.step(Some(&mut policy), &mut out).unwrap();
        }
        // Push acts +1 (agent units); the env moves by 1 / 2 per step: 1.5, 2, 2.5, 3.
        assert!(out.transitions.iter().all(|t| t.action == [1.0]));
        let next: Vec<f32> = out.transitions.iter().map(|t| t.next_obs[0]).collect();
        assert_eq!(next, [1.5, 2.0, 2.5, 3.0]);
        assert_eq!(out.finished[0].1.episode_return, 1.0);
        // s < 1: a / s is clipped to the env's [-1, 1].
        let mut r = Rollout::new(vec![Line::boxed()], 1, settings(false))
            .with_action_scale(Some(vec![0.5]))
            .unwrap();
        r.begin(0, lease(2, LeaseKind::DemoState, vec![0.0], 1, 1))
            .unwrap();
        out.clear();
        r.step(Some(&mut policy), &mut out).unwrap();
        assert_eq!(
            (out.transitions[0].action[0], out.transitions[0].next_obs[0]),
            (1.0, 1.0)
        );
        // A scale that does not fit the env is refused.
        for bad in [vec![1.0, 1.0], vec![0.0], vec![f32::NAN]] {
            let err = Rollout::new(vec![Line::boxed()], 1, settings(false))
                .with_action_scale(Some(bad))
                .err()
                .expect("refused");
            assert!(
                matches!(err, RolloutError::ActionScale { env: 0, .. }),
                "{err}"
            );
        }
    }

    #[test]
    fn seeds_differ_per_actor_and_env_and_are_stable() {
        let a = derive_seed(1, 0, 0);
        assert_eq!(a, derive_seed(1, 0, 0));
        let all = [
            a,
            derive_seed(1, 0, 1),
            derive_seed(1, 1, 0),
            derive_seed(2, 0, 0),
            derive_seed(1, 1, 1),
        ];
        for i in 0..all.len() {
            for j in i + 1..all.len() {
                assert_ne!(all[i], all[j], "{i} vs {j}");
            }
        }
    }

    #[test]
    fn uniform_actions_are_reproducible_from_the_seeds() {
        let actions = |seed| {
            let mut r = Rollout::new(vec![Line::boxed()], seed, settings(false));
            r.begin(0, lease(1, LeaseKind::DemoState, vec![0.0], 5, 1))
                .unwrap();
            let mut out = StepOutput::default();
            for _ in 0..5 {
                r.step(None, &mut out).unwrap();
            }
            out.transitions
                .iter()
                .map(|t| t.action[0])
                .collect::<Vec<_>>()
        };
        assert_eq!(actions(3), actions(3));
        assert_ne!(actions(3), actions(4));
    }
}
