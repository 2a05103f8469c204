//! The tonic implementation of `rfcl.v1.Curriculum`: thin handlers that convert wire messages once,
//! at the top of each RPC, call into the [`ServerState`](crate::state::ServerState) under the
//! shared lock, and convert the answers back (stage statuses to `StageEvent`s, errors to gRPC
//! statuses).
use std::pin::Pin;

use rfcl_core::lease::{AcquireRequest, EpisodeReport, ResetLease};
use rfcl_proto::v1;
use tonic::{Request, Response, Status};

use crate::leases::ReportRefusal;
use crate::service::Shared;
use crate::state::{unix_now, ReportError, ReportResult};
use crate::{CurriculumError, StageStatus};

/// The wire form of where the run stands.
fn stage_event(status: StageStatus) -> v1::StageEvent {
    v1::StageEvent {
        stage: status.number(),
        stage_epoch: status.epoch,
        at_env_steps: status.stage_1_end_env_steps.unwrap_or(0),
        finished: status.finished(),
    }
}

/// Each refusal gets its own code, so an actor can tell a report it may simply drop (a repeat, an
/// expired or unknown lease, an ended stage epoch) from one that shows a bug on its side (another
/// actor's lease, more steps than the lease allows).
impl From<ReportError> for Status {
    fn from(err: ReportError) -> Status {
        match &err {
            ReportError::Refused(ReportRefusal::Duplicate(_)) => {
                Status::already_exists(err.to_string())
            }
            ReportError::Refused(ReportRefusal::Unknown(_)) => Status::not_found(err.to_string()),
            ReportError::Refused(ReportRefusal::NotHolder { .. }) => {
                Status::permission_denied(err.to_string())
            }
            ReportError::Refused(ReportRefusal::OverTimeLimit { .. }) => {
                Status::invalid_argument(err.to_string())
            }
            ReportError::Refused(_) | ReportError::StageEpochOver { .. } => {
                Status::failed_precondition(err.to_string())
            }
            ReportError::Curriculum(_) => Status::internal(err.to_string()),
        }
    }
}

/// The tonic service.
pub struct CurriculumService {
    pub shared: Shared,
}

impl CurriculumService {
    /// Applies a report and, if asked, hands out the next lease, under one lock. A refused report
    /// (other than a repeat, which is acknowledged) fails with its status and hands out nothing.
    fn report_then_acquire(
        &self,
        report: EpisodeReport,
        next: Option<AcquireRequest>,
    ) -> Result<(v1::ReportAck, Option<ResetLease>), Status> {
        let now = unix_now();
        let (result, lease, status, snapshot_due) = {
            let mut state = self.shared.lock();
            let result = match state.report(&report, &self.shared.cfg, now) {
                Ok(r) => Ok(r),
                // A repeated report is acknowledged and changes nothing (exactly-once).
                Err(ReportError::Refused(ReportRefusal::Duplicate(_))) => Ok(ReportResult {
                    applied: false,
                    stage_change: None,
                    eval: false,
                }),
                Err(e) => Err(e),
            };
            let result = result.map(|r| match r.eval {
                true => ReportResult {
                    stage_change: state.apply_stop_rule(&self.shared.cfg),
                    ..r
                },
                false => r,
            });
            let lease = match (&result, next) {
                (Ok(_), Some(req)) => {
                    Some(state.acquire(req, &self.shared.cfg, &self.shared.demos, now))
                }
                _ => None,
            };
            let due =
                state.reports_since_snapshot >= self.shared.cfg.service.snapshot_every_reports;
            (result, lease, state.stage_status(), due)
        };
        if snapshot_due {
            self.shared.snapshot_due.notify_one();
        }
        let result = result?;
        if let Some(change) = result.stage_change {
            let ev = stage_event(change);
            tracing::info!(
                stage = ev.stage,
                epoch = ev.stage_epoch,
                env_steps = ev.at_env_steps,
                "stage change"
            );
            self.shared.stage_tx.send_replace(change);
        }
        let ack = v1::ReportAck {
            applied: result.applied,
            stage: status.number(),
            stage_epoch: status.epoch,
        };
        let lease = lease.transpose().map_err(acquire_status)?;
        Ok((ack, lease))
    }

    fn count_malformed(&self) {
        self.shared.lock().stats.malformed_reports += 1;
    }
}

fn acquire_status(err: CurriculumError) -> Status {
    match err {
        CurriculumError::Finished => Status::failed_precondition(err.to_string()),
        e => Status::internal(e.to_string()),
    }
}

/// A stream that ends as soon as `stop` resolves.
struct UntilStopped<S> {
    inner: S,
    stop: Pin<Box<dyn std::future::Future<Output = ()> + Send>>,
    /// `stop` resolved: it must not be polled again.
    ended: bool,
}

impl<S: tokio_stream::Stream + Unpin> tokio_stream::Stream for UntilStopped<S> {
    type Item = S::Item;

    fn poll_next(
        mut self: Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<S::Item>> {
        if self.ended || self.stop.as_mut().poll(cx).is_ready() {
            self.ended = true;
            return std::task::Poll::Ready(None);
        }
        Pin::new(&mut self.inner).poll_next(cx)
    }
}

type StageStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<v1::StageEvent, Status>> + Send>>;

#[tonic::async_trait]
impl v1::curriculum_server::Curriculum for CurriculumService {
    async fn acquire(
        &self,
        request: Request<v1::AcquireRequest>,
    ) -> Result<Response<v1::ResetLease>, Status> {
        let req = AcquireRequest::from(request.into_inner());
        let lease =
            self.shared
                .lock()
                .acquire(req, &self.shared.cfg, &self.shared.demos, unix_now());
        lease
            .map(|l| Response::new(l.into()))
            .map_err(acquire_status)
    }

    async fn report(
        &self,
        request: Request<v1::EpisodeReport>,
    ) -> Result<Response<v1::ReportAck>, Status> {
        let report = EpisodeReport::try_from(request.into_inner())
            .inspect_err(|_| self.count_malformed())?;
        let (ack, _) = self.report_then_acquire(report, None)?;
        Ok(Response::new(ack))
    }

    async fn report_and_acquire(
        &self,
        request: Request<v1::ReportAndAcquireRequest>,
    ) -> Result<Response<v1::ReportAndAcquireReply>, Status> {
        let (report, next) = rfcl_proto::convert::report_and_acquire(request.into_inner())
            .inspect_err(|_| self.count_malformed())?;
        let (ack, lease) = self.report_then_acquire(report, Some(next))?;
        Ok(Response::new(v1::ReportAndAcquireReply {
            ack: Some(ack),
            lease: lease.map(Into::into),
        }))
    }

    type WatchStageStream = StageStream;

    async fn watch_stage(
        &self,
        request: Request<v1::WatchStageRequest>,
    ) -> Result<Response<StageStream>, Status> {
        if let Some(addr) = rfcl_proto::convert::learner_addr(request.get_ref())? {
            self.shared.learner.announce(addr);
        }
        let rx = self.shared.stage_tx.subscribe();
        let stream = tokio_stream::wrappers::WatchStream::new(rx);
        // The stream ends (status OK) when the server stops: a subscriber never holds up a stop.
        let mut stopping = self.shared.stopping.subscribe();
        let stream = UntilStopped {
            inner: stream,
            stop: Box::pin(async move {
                let _ = stopping.wait_for(|s| *s).await;
            }),
            ended: false,
        };
        Ok(Response::new(Box::pin(tokio_stream::StreamExt::map(
            stream,
            |status| Ok(stage_event(status)),
        ))))
    }

    async fn get_state(
        &self,
        _: Request<v1::GetStateRequest>,
    ) -> Result<Response<v1::CurriculumState>, Status> {
        let run = self.shared.view().run;
        let json = serde_json::to_string(&run).map_err(|e| Status::internal(e.to_string()))?;
        let last_complete_eval_env_steps = crate::stop::last_complete_env_steps(
            &self.shared.lock().stats.evals,
            rfcl_core::config::episodes_per_eval(&self.shared.cfg),
        )
        .unwrap_or(0);
        Ok(Response::new(v1::CurriculumState {
            json,
            stage: run.stage,
            stage_epoch: run.stage_epoch,
            last_complete_eval_env_steps,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Stage;

    #[test]
    fn a_finished_run_keeps_the_number_of_the_stage_it_finished_in_on_the_wire() {
        let status = StageStatus {
            stage: Stage::Finished,
            curriculum_stage: Stage::Forward,
            epoch: 2,
            stage_1_end_env_steps: Some(500),
        };
        assert_eq!(
            stage_event(status),
            v1::StageEvent {
                stage: 2,
                stage_epoch: 2,
                at_env_steps: 500,
                finished: true,
            }
        );
        let running = StageStatus {
            stage: Stage::Reverse,
            curriculum_stage: Stage::Reverse,
            epoch: 0,
            stage_1_end_env_steps: None,
        };
        assert_eq!(
            stage_event(running),
            v1::StageEvent {
                stage: 1,
                stage_epoch: 0,
                at_env_steps: 0,
                finished: false,
            }
        );
    }
}
