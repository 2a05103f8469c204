//! What `rfcl train` knows of its running services, from their gRPC answers: the learner's
//! counters (Health) and update rate, the curriculum's state (GetState) and the evaluations it
//! completes, and how long each service has gone unanswered.
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use rfcl_core::run_state::RunState;
use rfcl_proto::auth::AuthChannel;
use rfcl_proto::v1;
use rfcl_proto::v1::curriculum_client::CurriculumClient;
use rfcl_proto::v1::learner_client::LearnerClient;
use tonic::transport::Channel;

use super::policy::{Service, Silence, SilenceAction};
use rfcl_core::final_counters::LearnerCounts;

use super::progress::{CompleteEval, CountersSource, EvalTracker, LearnerCounters};

/// A service silent this long is said to be so (it is killed at `service.hang_timeout_s`).
pub const SILENCE_WARN_S: f64 = 15.0;

/// The learner's updates per second, smoothed over its Health replies.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct UpdateRate {
    pub per_s: f64,
    last: Option<(f64, u64)>,
}

impl UpdateRate {
    /// The learner had done `updates` at time `t_s`. The first reply (and the first after a
    /// restart: [`UpdateRate::restart`]) only sets the reference; a counter that went back leaves
    /// the rate as it was.
    pub fn observe(&mut self, t_s: f64, updates: u64) {
        if let Some((t, before)) = self.last {
            let dt = t_s - t;
            if dt > 0.0 && updates >= before {
                let rate = (updates - before) as f64 / dt;
                self.per_s = 0.8 * self.per_s + 0.2 * rate;
            }
        }
        self.last = Some((t_s, updates));
    }

    /// The learner restarted: its counters start again from its checkpoint.
    pub fn restart(&mut self) {
        self.last = None;
    }
}

/// The services' clients and their latest answers.
pub struct Monitor {
    curriculum: CurriculumClient<AuthChannel>,
    learner: LearnerClient<AuthChannel>,
    started: Instant,
    pub counters: LearnerCounters,
    pub rate: UpdateRate,
    /// The curriculum server's latest state.
    pub last_view: Option<RunState>,
    pub evals: EvalTracker,
    server_silence: Silence,
    learner_silence: Silence,
}

impl Monitor {
    pub fn new(
        curriculum: CurriculumClient<AuthChannel>,
        learner: LearnerClient<AuthChannel>,
        evals: EvalTracker,
    ) -> Self {
        Self {
            curriculum,
            learner,
            started: Instant::now(),
            counters: LearnerCounters::default(),
            rate: UpdateRate::default(),
            last_view: None,
            evals,
            server_silence: Silence::default(),
            learner_silence: Silence::default(),
        }
    }

    /// Takes the learner's counters from its Health; false when it did not answer.
    pub async fn poll_health(&mut self) -> bool {
        let mut client = self.learner.clone();
        let Ok(Ok(reply)) =
            tokio::time::timeout(Duration::from_secs(2), client.health(v1::HealthRequest {})).await
        else {
            return false;
        };
        let h = reply.into_inner();
        self.rate
            .observe(self.started.elapsed().as_secs_f64(), h.updates);
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

    /// The curriculum's state, `None` when the server did not answer.
    async fn fetch_state(&self) -> Option<RunState> {
        fetch_run_state(&mut self.curriculum.clone()).await
    }

    /// Asks the curriculum server for its state and keeps it; the evaluations it completed since
    /// the last call, or `None` when the server did not answer.
    pub async fn poll_state(&mut self, wall_s: f64) -> Option<Vec<CompleteEval>> {
        let view = self.fetch_state().await?;
        let fresh = self.evals.update(&view.evals, wall_s);
        self.last_view = Some(view);
        Some(fresh)
    }

    /// Counts `service`'s answer or silence at run wall time `now`: what to do about it.
    pub fn heard(
        &mut self,
        service: Service,
        answered: bool,
        now: f64,
        kill_after_s: Option<f64>,
    ) -> SilenceAction {
        let silence = match service {
            Service::Curriculum => &mut self.server_silence,
            Service::Learner => &mut self.learner_silence,
        };
        if answered {
            silence.answered();
            SilenceAction::Wait
        } else {
            silence.silent(now, SILENCE_WARN_S, kill_after_s)
        }
    }

    /// The counters a restart can roll back: the learner's env steps and updates (its last
    /// Health), the curriculum's episode reports (its last state).
    pub fn rollback_counters(&self) -> [u64; 3] {
        [
            self.counters.counts.env_steps,
            self.counters.counts.updates,
            self.last_view.as_ref().map_or(0, |v| v.episodes),
        ]
    }

    /// The curriculum's stage as last seen (1 before any answer).
    pub fn stage(&self) -> u32 {
        self.last_view.as_ref().map_or(1, |v| v.stage)
    }

    /// Episodes reported to the curriculum's evaluations so far.
    pub fn eval_episodes_reported(&self) -> u64 {
        self.last_view
            .as_ref()
            .map_or(0, |v| v.evals.iter().map(|p| p.episodes).sum())
    }
}

/// A lazily connecting channel to `url`.
pub fn channel(url: &str) -> Result<Channel> {
    Ok(tonic::transport::Endpoint::from_shared(url.to_string())
        .with_context(|| format!("invalid address {url}"))?
        .connect_timeout(Duration::from_secs(3))
        .connect_lazy())
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_update_rate_is_smoothed_and_survives_a_restart() {
        let mut r = UpdateRate::default();
        r.observe(0.0, 100);
        assert_eq!(r.per_s, 0.0, "one reply is no rate");
        // 50 updates in 1 s: 0.2 of the way from 0 to 50.
        r.observe(1.0, 150);
        assert_eq!(r.per_s, 10.0);
        // 100 in 2 s: 0.8 * 10 + 0.2 * 50.
        r.observe(3.0, 250);
        assert_eq!(r.per_s, 18.0);
        // A restarted learner counts from its checkpoint: the rate stays, the reference moves.
        r.restart();
        r.observe(4.0, 200);
        assert_eq!(r.per_s, 18.0);
        r.observe(5.0, 245);
        assert_eq!(r.per_s, 0.8 * 18.0 + 0.2 * 45.0);
        // A counter that went back, or no time between replies, changes nothing.
        let before = r.per_s;
        r.observe(6.0, 10);
        r.observe(6.0, 20);
        assert_eq!(r.per_s, before);
    }
}
