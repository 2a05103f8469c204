//! The dashboard's learner panel: the learner announces where it serves when it subscribes to
//! WatchStage, and the server polls its Health RPC over gRPC with the run's token. Nothing is
//! shared with the learner but the wire.
use std::sync::Mutex;
use std::time::Duration;

use rfcl_proto::auth::ClientAuth;
use rfcl_proto::v1;
use rfcl_proto::v1::learner_client::LearnerClient;
use tonic::transport::{Channel, Endpoint};

use crate::dashboard::{LearnerPanel, LearnerWindowView, TimeShares};
use crate::state::unix_now;

/// How often the server asks the learner. The learner's window is its progress line's (10 s), so
/// a faster poll only shows its counters move.
pub const POLL_EVERY: Duration = Duration::from_secs(2);
/// Connect and call timeout of one poll.
const POLL_TIMEOUT: Duration = Duration::from_secs(2);

/// What the server knows of the learner: where it serves and its last answer.
#[derive(Debug, Default)]
pub struct LearnerLink {
    /// The credentials for calling the learner; `None`: no polling (the panel says so).
    auth: Option<ClientAuth>,
    state: Mutex<LinkState>,
}

#[derive(Debug, Default)]
struct LinkState {
    addr: Option<String>,
    /// The last answer, as the panel shows it, and when it came (unix seconds).
    answer: Option<(f64, LearnerPanel)>,
    error: Option<String>,
}

impl LearnerLink {
    pub fn new(auth: Option<ClientAuth>) -> Self {
        LearnerLink {
            auth,
            state: Mutex::default(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, LinkState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A learner said it serves at `addr` (a URL checked by the wire conversion).
    pub fn announce(&self, addr: String) {
        let mut state = self.lock();
        if state.addr.as_deref() != Some(&addr) {
            tracing::info!("the learner serves at {addr}: the dashboard polls its Health there");
            state.addr = Some(addr);
            state.answer = None;
            state.error = None;
        }
    }

    /// The panel as of `now` (unix seconds); `None` until a learner announced itself.
    pub fn panel(&self, now: f64) -> Option<LearnerPanel> {
        let state = self.lock();
        let addr = state.addr.clone()?;
        let mut panel = match &state.answer {
            Some((at, answer)) => LearnerPanel {
                seconds_since_answer: Some((now - at).max(0.0)),
                ..answer.clone()
            },
            None => LearnerPanel::default(),
        };
        panel.address = addr;
        panel.error = match (&self.auth, &state.error) {
            (None, _) => Some("not polled: the server has no client credentials".into()),
            (Some(_), e) => e.clone(),
        };
        // A learner that does not answer is not well, whatever it said last.
        panel.ok &= panel.error.is_none();
        Some(panel)
    }

    fn record(&self, addr: &str, outcome: Result<v1::HealthReply, String>) {
        let mut state = self.lock();
        // A newer announcement replaced the address while this poll ran: its answer is stale.
        if state.addr.as_deref() != Some(addr) {
            return;
        }
        match outcome {
            Ok(reply) => {
                state.answer = Some((unix_now(), panel_from_wire(reply)));
                state.error = None;
            }
            Err(e) => state.error = Some(e),
        }
    }

    /// Polls the announced learner every [`POLL_EVERY`] until `stop` resolves; a failed poll is
    /// shown on the panel and retried, never fatal (the learner may be restarting).
    pub async fn poll_loop(
        &self,
        stop: impl std::future::Future<Output = ()>,
    ) -> anyhow::Result<()> {
        let Some(auth) = self.auth.clone() else {
            stop.await;
            return Ok(());
        };
        tokio::pin!(stop);
        let mut tick = tokio::time::interval(POLL_EVERY);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut channel: Option<(String, Channel)> = None;
        loop {
            tokio::select! { _ = tick.tick() => {}, _ = &mut stop => return Ok(()) }
            let Some(addr) = self.lock().addr.clone() else {
                continue;
            };
            if channel.as_ref().is_none_or(|(a, _)| *a != addr) {
                channel = match connect(&addr, &auth).await {
                    Ok(c) => Some((addr.clone(), c)),
                    Err(e) => {
                        self.record(&addr, Err(e));
                        continue;
                    }
                };
            }
            let Some((_, ch)) = &channel else { continue };
            let mut client = LearnerClient::new(auth.wrap(ch.clone()));
            let call = client.health(v1::HealthRequest {});
            let outcome = match tokio::time::timeout(POLL_TIMEOUT, call).await {
                Ok(Ok(reply)) => Ok(reply.into_inner()),
                Ok(Err(status)) => Err(format!(
                    "Health at {addr}: {:?}: {}",
                    status.code(),
                    status.message()
                )),
                Err(_) => Err(format!(
                    "Health at {addr}: no answer within {} s",
                    POLL_TIMEOUT.as_secs()
                )),
            };
            self.record(&addr, outcome);
        }
    }
}

async fn connect(addr: &str, auth: &ClientAuth) -> Result<Channel, String> {
    let endpoint = Endpoint::from_shared(addr.to_string())
        .and_then(|e| {
            auth.endpoint(rfcl_proto::link::client(
                e.connect_timeout(POLL_TIMEOUT).timeout(POLL_TIMEOUT),
            ))
        })
        .map_err(|e| format!("the learner's address {addr}: {e}"))?;
    // Lazy: a learner that is down now is reached once it is back, on the same channel.
    Ok(endpoint.connect_lazy())
}

/// The learner's Health reply as the panel shows it (the one conversion of that message).
fn panel_from_wire(reply: v1::HealthReply) -> LearnerPanel {
    LearnerPanel {
        address: String::new(),
        seconds_since_answer: None,
        error: None,
        ok: reply.ok,
        env_steps: reply.env_steps,
        critic_updates: reply.updates,
        policy_version: reply.policy_version,
        run_id: reply.run_id,
        window: reply.window.map(|w| LearnerWindowView {
            seconds: w.seconds,
            updates_per_s: w.updates_per_s,
            env_steps_per_s: w.env_steps_per_s,
            utd: w.utd,
            utd_target: w.utd_target,
            policy_lag_max: w.policy_lag_max,
            critic_loss: w.critic_loss,
            actor_loss: w.actor_loss,
            q: w.q,
            entropy: w.entropy,
            temperature: w.temperature,
            time_shares: time_shares(
                w.seconds,
                [
                    w.wait_s,
                    w.ingest_s,
                    w.update_s,
                    w.publish_s,
                    w.checkpoint_s,
                ],
            ),
        }),
    }
}

/// Seconds per activity `[wait, ingest, update, publish, checkpoint]` as fractions of a window
/// of `seconds`, each within [0, 1] (a window of no length has none).
pub fn time_shares(seconds: f64, per_activity: [f64; 5]) -> TimeShares {
    let share = |s: f64| {
        if seconds > 0.0 && s.is_finite() {
            (s / seconds).clamp(0.0, 1.0)
        } else {
            0.0
        }
    };
    let [wait, ingest, update, publish, checkpoint] = per_activity.map(share);
    TimeShares {
        waiting: wait,
        ingesting: ingest,
        updating: update,
        publishing: publish,
        checkpointing: checkpoint,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_shares_are_fractions_of_the_window() {
        // A 10 s window: 1 s waiting, 0.5 s ingesting, 8 s updating, 0.25 s publishing, 0 s
        // checkpointing.
        let s = time_shares(10.0, [1.0, 0.5, 8.0, 0.25, 0.0]);
        assert_eq!(
            (
                s.waiting,
                s.ingesting,
                s.updating,
                s.publishing,
                s.checkpointing
            ),
            (0.1, 0.05, 0.8, 0.025, 0.0)
        );
        // Clock skew cannot make a share exceed the window; an empty window has none.
        assert_eq!(time_shares(1.0, [2.0, 0.0, 0.0, 0.0, 0.0]).waiting, 1.0);
        assert_eq!(time_shares(0.0, [1.0; 5]), TimeShares::default());
    }

    #[test]
    fn the_panel_appears_on_announcement_and_keeps_the_last_answer_through_failures() {
        let link = LearnerLink::new(Some(ClientAuth::plain(rfcl_proto::auth::Token::random())));
        assert_eq!(link.panel(0.0), None);
        link.announce("http://learner:50052".into());
        let panel = link.panel(0.0).unwrap();
        assert_eq!(panel.address, "http://learner:50052");
        assert_eq!(panel.seconds_since_answer, None);

        let reply = v1::HealthReply {
            ok: true,
            updates: 320,
            env_steps: 20,
            policy_version: 7,
            window: Some(v1::LearnerWindow {
                seconds: 10.0,
                updates_per_s: 32.0,
                critic_loss: Some(0.5),
                update_s: 5.0,
                ..Default::default()
            }),
            ..Default::default()
        };
        link.record("http://learner:50052", Ok(reply.clone()));
        assert!(link.panel(unix_now()).unwrap().ok);
        link.record("http://learner:50052", Err("Health at …: no answer".into()));
        let now = unix_now() + 3.0;
        let panel = link.panel(now).unwrap();
        assert!(panel.seconds_since_answer.unwrap() >= 3.0);
        assert_eq!(panel.error.as_deref(), Some("Health at …: no answer"));
        assert!(!panel.ok, "a learner that does not answer is not ok");
        assert_eq!((panel.critic_updates, panel.policy_version), (320, 7));
        let w = panel.window.unwrap();
        assert_eq!(
            (w.updates_per_s, w.critic_loss, w.actor_loss),
            (32.0, Some(0.5), None)
        );
        assert_eq!(w.time_shares.updating, 0.5);

        // An answer from an address the learner no longer announces is dropped.
        link.announce("http://learner:50053".into());
        link.record("http://learner:50052", Ok(v1::HealthReply::default()));
        assert_eq!(link.panel(now).unwrap().address, "http://learner:50053");
        assert_eq!(link.panel(now).unwrap().error, None);
    }

    #[test]
    fn without_credentials_the_panel_says_it_is_not_polled() {
        let link = LearnerLink::new(None);
        link.announce("http://learner:50052".into());
        assert!(link
            .panel(0.0)
            .unwrap()
            .error
            .unwrap()
            .contains("not polled"));
    }
}
