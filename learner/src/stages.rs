//! The learner's subscription to the curriculum server's stage announcements (`WatchStage`,
//! spec 4; docs/LEARNER.md "Stage transition"): the first event is the current stage, then every
//! change. A broken stream is re-opened (the curriculum server restarts from its snapshot), so
//! the training thread always learns of every stage epoch.
//!
//! This is the edge where v1's `StageEvent` becomes the learner's [`StageAnnouncement`]: the rest
//! of the learner sees a [`Stage`], not a stage number.
use std::time::Duration;

use rfcl_proto::auth::ClientAuth;
use rfcl_proto::v1;
use rfcl_proto::v1::curriculum_client::CurriculumClient;
use thiserror::Error;
use tokio::sync::{mpsc, watch};
use tonic::transport::{Channel, Endpoint};
use tonic::Streaming;

/// The two stages of RFCL.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Stage 1: the per-demo reverse curriculum (spec 2).
    Reverse,
    /// Stage 2: the seed-based forward curriculum (spec 3).
    Forward,
}

impl Stage {
    /// A stage number of v1 (`StageEvent.stage`) or of a checkpoint: 1 is the reverse
    /// curriculum (as is 0, an unset field), 2 and above the forward one.
    pub fn from_number(number: u32) -> Self {
        if number >= 2 {
            Self::Forward
        } else {
            Self::Reverse
        }
    }

    /// The stage's number (1 or 2), as checkpoints, `metrics.csv` and Prometheus show it.
    pub fn number(self) -> u32 {
        match self {
            Self::Reverse => 1,
            Self::Forward => 2,
        }
    }
}

/// A stage announcement of the curriculum server: the stage, its epoch (one per stage change,
/// counted by the curriculum server), and whether the run is over.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StageAnnouncement {
    pub stage: Stage,
    pub epoch: u64,
    /// The curriculum server ended the run (`train.stage_1_only`).
    pub finished: bool,
}

impl From<&v1::StageEvent> for StageAnnouncement {
    fn from(event: &v1::StageEvent) -> Self {
        Self {
            stage: Stage::from_number(event.stage),
            epoch: event.stage_epoch,
            finished: event.finished,
        }
    }
}

/// Pause between reconnection attempts.
pub const RECONNECT_EVERY: Duration = Duration::from_secs(1);

#[derive(Debug, Error)]
pub enum StageWatchError {
    #[error("invalid curriculum server address {addr:?}")]
    Address {
        addr: String,
        source: tonic::transport::Error,
    },
    #[error("cannot reach the curriculum server at {addr}")]
    Connect {
        addr: String,
        source: tonic::transport::Error,
    },
    #[error("the curriculum server at {addr} refused WatchStage: {status}")]
    Refused { addr: String, status: tonic::Status },
    #[error("the curriculum server at {addr} closed WatchStage before announcing the stage")]
    Closed { addr: String },
    #[error("no answer from the curriculum server at {addr} within {timeout:?}")]
    Timeout { addr: String, timeout: Duration },
}

/// Opens `WatchStage` on the curriculum server at `addr` and returns the stream with its first
/// announcement (the current stage). `learner_addr` (empty: not serving yet) tells the server
/// where to poll this learner's Health for its dashboard.
pub async fn open(
    addr: &str,
    auth: &ClientAuth,
    timeout: Duration,
    learner_addr: &str,
) -> Result<(Streaming<v1::StageEvent>, StageAnnouncement), StageWatchError> {
    let attempt = async {
        let endpoint = Endpoint::from_shared(addr.to_string())
            .and_then(|e| auth.endpoint(rfcl_proto::link::client(e.connect_timeout(timeout))))
            .map_err(|source| StageWatchError::Address {
                addr: addr.into(),
                source,
            })?;
        let channel: Channel =
            endpoint
                .connect()
                .await
                .map_err(|source| StageWatchError::Connect {
                    addr: addr.into(),
                    source,
                })?;
        let mut stream = CurriculumClient::new(auth.wrap(channel))
            .watch_stage(v1::WatchStageRequest {
                learner_addr: learner_addr.to_string(),
            })
            .await
            .map_err(|status| StageWatchError::Refused {
                addr: addr.into(),
                status,
            })?
            .into_inner();
        match stream.message().await {
            Ok(Some(first)) => Ok((stream, StageAnnouncement::from(&first))),
            Ok(None) => Err(StageWatchError::Closed { addr: addr.into() }),
            Err(status) => Err(StageWatchError::Refused {
                addr: addr.into(),
                status,
            }),
        }
    };
    tokio::time::timeout(timeout, attempt)
        .await
        .map_err(|_| StageWatchError::Timeout {
            addr: addr.into(),
            timeout,
        })?
}

/// Forwards every stage event of `stream` (and of re-opened streams after a break) to `events`
/// as an announcement, until `stopping` turns true or the receiver is gone. Re-opened streams
/// announce `learner_addr` again (a restarted server learns it from them).
pub async fn follow(
    addr: String,
    auth: ClientAuth,
    learner_addr: String,
    mut stream: Streaming<v1::StageEvent>,
    events: mpsc::UnboundedSender<StageAnnouncement>,
    mut stopping: watch::Receiver<bool>,
) {
    loop {
        let message = tokio::select! {
            m = stream.message() => m,
            _ = stopping.wait_for(|s| *s) => return,
        };
        match message {
            Ok(Some(event)) => {
                if events.send(StageAnnouncement::from(&event)).is_err() {
                    return;
                }
                continue;
            }
            Ok(None) => {
                tracing::warn!("the curriculum server at {addr} closed WatchStage; reconnecting")
            }
            Err(status) => tracing::warn!("WatchStage from {addr} broke ({status}); reconnecting"),
        }
        loop {
            tokio::select! {
                _ = tokio::time::sleep(RECONNECT_EVERY) => {}
                _ = stopping.wait_for(|s| *s) => return,
            }
            match open(&addr, &auth, Duration::from_secs(5), &learner_addr).await {
                Ok((next, first)) => {
                    tracing::info!("WatchStage re-opened at {addr}");
                    if events.send(first).is_err() {
                        return;
                    }
                    stream = next;
                    break;
                }
                Err(e) => tracing::debug!("{}", crate::error::chain(&e)),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn v1_stage_numbers_become_stages() {
        let event = |stage, finished| v1::StageEvent {
            stage,
            stage_epoch: 3,
            at_env_steps: 100,
            finished,
        };
        for (number, stage) in [
            (0, Stage::Reverse),
            (1, Stage::Reverse),
            (2, Stage::Forward),
        ] {
            let announcement = StageAnnouncement::from(&event(number, false));
            assert_eq!(announcement.stage, stage);
            assert_eq!(announcement.epoch, 3);
            assert!(!announcement.finished);
        }
        assert!(StageAnnouncement::from(&event(1, true)).finished);
        assert_eq!(Stage::Reverse.number(), 1);
        assert_eq!(Stage::Forward.number(), 2);
    }
}
