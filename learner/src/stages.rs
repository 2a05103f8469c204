//! The learner's subscription to the curriculum server's stage announcements (`WatchStage`,
//! spec 4, ARCHITECTURE "Semantics"): the first event is the current stage, then every change.
//! A broken stream is re-opened (the curriculum server restarts from its snapshot), so the
//! training thread always learns of every stage epoch.
use std::time::Duration;

use rfcl_proto::auth::ClientAuth;
use rfcl_proto::v1;
use rfcl_proto::v1::curriculum_client::CurriculumClient;
use thiserror::Error;
use tokio::sync::{mpsc, watch};
use tonic::transport::{Channel, Endpoint};
use tonic::Streaming;

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
/// event (the current stage).
pub async fn open(
    addr: &str,
    auth: &ClientAuth,
    timeout: Duration,
) -> Result<(Streaming<v1::StageEvent>, v1::StageEvent), StageWatchError> {
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
            .watch_stage(v1::WatchStageRequest {})
            .await
            .map_err(|status| StageWatchError::Refused {
                addr: addr.into(),
                status,
            })?
            .into_inner();
        match stream.message().await {
            Ok(Some(first)) => Ok((stream, first)),
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
/// until `stopping` turns true or the receiver is gone.
pub async fn follow(
    addr: String,
    auth: ClientAuth,
    mut stream: Streaming<v1::StageEvent>,
    events: mpsc::UnboundedSender<v1::StageEvent>,
    mut stopping: watch::Receiver<bool>,
) {
    loop {
        let message = tokio::select! {
            m = stream.message() => m,
            _ = stopping.wait_for(|s| *s) => return,
        };
        match message {
            Ok(Some(event)) => {
                if events.send(event).is_err() {
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
            match open(&addr, &auth, Duration::from_secs(5)).await {
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
