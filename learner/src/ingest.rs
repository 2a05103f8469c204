//! Transition ingest: validation of transition records at the edge, whichever transport brought
//! them (a gRPC `TransitionBatch`, a shared-memory frame: [`validate_records`] is the one check),
//! the items that travel through the bounded queue to the training thread, and the counts per
//! transport ([`IngestCounters`]): every queue is bounded and every drop is counted
//! (docs/DESIGN.md, "The path of a transition").
//!
//! A batch is validated whole before any of it is queued; a malformed one is refused (gRPC: with
//! `INVALID_ARGUMENT` naming the field; shared memory: counted and logged). What the training thread does with each record (stored,
//! or dropped because its stage epoch is over, spec 4) is tallied per stream, so
//! `PushTransitions` answers with exact counts once every batch of the stream was handled.
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use rfcl_core::transition::{RecordLayout, RecordView};
use rfcl_proto::convert::WireError;
use rfcl_proto::v1;
use tokio::sync::watch;

const MESSAGE: &str = "TransitionBatch";

/// What a valid batch told us beyond its records.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BatchInfo {
    pub count: usize,
    /// The oldest policy version that acted in the batch (for the lag report).
    pub min_policy_version: u64,
}

/// Checks a batch against the learner's dims (spec 5.6 for the mask): dims equal to the run's,
/// `records` exactly `count` records long, every number finite, `mask` 0 or 1, every action in
/// [−1, 1] (agent units: the policy's tanh range), and no stage epoch beyond `max_stage_epoch`
/// (the learner's epoch + 1: a stage change can be announced to an actor before the learner,
/// never two).
pub fn validate_batch(
    batch: &v1::TransitionBatch,
    layout: RecordLayout,
    max_stage_epoch: u64,
) -> Result<BatchInfo, WireError> {
    validate_records(
        MESSAGE,
        RecordsHeader {
            obs_dim: batch.obs_dim,
            action_dim: batch.action_dim,
            count: batch.count,
        },
        &batch.records,
        layout,
        max_stage_epoch,
    )
}

/// What a transport says about the records it carries (a `TransitionBatch`'s fields, or a
/// shared-memory frame's header).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RecordsHeader {
    pub obs_dim: u32,
    pub action_dim: u32,
    pub count: u32,
}

/// The checks of [`validate_batch`] for records from any transport: both transports refuse
/// exactly the same records. `message` names the carrier in errors (`TransitionBatch`, or the
/// shared-memory frame).
pub fn validate_records(
    message: &'static str,
    header: RecordsHeader,
    records: &[u8],
    layout: RecordLayout,
    max_stage_epoch: u64,
) -> Result<BatchInfo, WireError> {
    let err = |field: &'static str, problem: String| WireError {
        message,
        field,
        problem,
    };
    for (field, got, run) in [
        ("obs_dim", header.obs_dim, layout.obs_dim),
        ("action_dim", header.action_dim, layout.action_dim),
    ] {
        if got as usize != run {
            return Err(err(
                field,
                format!("{got} differs from the run's {field} {run}"),
            ));
        }
    }
    let count = header.count as usize;
    let record_bytes = layout.record_bytes();
    if records.len() != count * record_bytes {
        return Err(err(
            "records",
            format!(
                "{} bytes, expected count {count} × {record_bytes} bytes per record (obs_dim {}, action_dim {})",
                records.len(),
                layout.obs_dim,
                layout.action_dim
            ),
        ));
    }
    let views = layout
        .view_batch(records)
        .map_err(|e| err("records", e.to_string()))?;
    let (d, a) = (layout.obs_dim, layout.action_dim);
    let (mut obs, mut action, mut next_obs) = (vec![0.0; d], vec![0.0; a], vec![0.0; d]);
    let mut min_policy_version = u64::MAX;
    for (i, view) in views.enumerate() {
        let bad = |problem: String| err("records", format!("record {i}: {problem}"));
        view.obs_into(&mut obs).map_err(|e| bad(e.to_string()))?;
        view.action_into(&mut action)
            .map_err(|e| bad(e.to_string()))?;
        view.next_obs_into(&mut next_obs)
            .map_err(|e| bad(e.to_string()))?;
        for (name, values) in [("obs", &obs), ("next_obs", &next_obs), ("action", &action)] {
            if let Some(j) = values.iter().position(|v| !v.is_finite()) {
                return Err(bad(format!("{name}[{j}] is {}", values[j])));
            }
        }
        if let Some(j) = action.iter().position(|v| v.abs() > 1.0) {
            return Err(bad(format!(
                "action[{j}] = {} is outside [-1, 1] (actions are in agent units)",
                action[j]
            )));
        }
        if !view.reward().is_finite() {
            return Err(bad(format!("reward is {}", view.reward())));
        }
        if view.mask() != 0.0 && view.mask() != 1.0 {
            return Err(bad(format!("mask is {}, expected 0 or 1", view.mask())));
        }
        if view.stage_epoch() > max_stage_epoch {
            return Err(bad(format!(
                "stage_epoch {} is ahead of the curriculum's (at most {max_stage_epoch} now)",
                view.stage_epoch()
            )));
        }
        min_policy_version = min_policy_version.min(view.policy_version());
    }
    Ok(BatchInfo {
        count,
        min_policy_version,
    })
}

/// The transports records arrive by.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Transport {
    /// `PushTransitions` (remote actors, or any actor with `--transport grpc`).
    Grpc,
    /// The iceoryx2 shared-memory service (actors on the learner's host).
    Shm,
}

impl Transport {
    pub fn as_str(self) -> &'static str {
        match self {
            Transport::Grpc => "grpc",
            Transport::Shm => "shm",
        }
    }
}

/// What one transport delivered to the ingest queue.
#[derive(Debug, Default)]
pub struct TransportCounts {
    /// Records validated and queued for the training thread.
    pub records: AtomicU64,
    /// Batches (gRPC messages, shared-memory frames) validated and queued.
    pub batches: AtomicU64,
    /// Batches refused as malformed (their records are not used).
    pub refused_batches: AtomicU64,
    /// Records known to be missing between the batches of one sender (shared memory: from the
    /// frames' sequence numbers). Always 0 for gRPC, whose losses the actor counts (unconfirmed).
    pub lost_records: AtomicU64,
}

/// Records and batches in per transport, so the processes themselves show which way transitions
/// came (Health, the learner's log, `rfcl train`'s summary). Metric names follow Prometheus:
/// `rfcl_learner_ingest_records_total{transport="shm"}` and so on ([`IngestCounters::lines`]).
#[derive(Debug, Default)]
pub struct IngestCounters {
    pub grpc: TransportCounts,
    pub shm: TransportCounts,
    /// Records queued (counted in `records` above) that the training thread never handled
    /// because the run stopped first, either transport.
    pub unused_records: AtomicU64,
}

/// One reading of [`IngestCounters`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IngestTotals {
    pub grpc_records: u64,
    pub grpc_batches: u64,
    pub shm_records: u64,
    pub shm_batches: u64,
    pub shm_lost_records: u64,
    pub refused_batches: u64,
    pub unused_records: u64,
}

impl IngestCounters {
    pub fn new() -> Arc<Self> {
        Arc::new(Self::default())
    }

    pub fn of(&self, transport: Transport) -> &TransportCounts {
        match transport {
            Transport::Grpc => &self.grpc,
            Transport::Shm => &self.shm,
        }
    }

    /// Counts one validated, queued batch of `records` records.
    pub fn queued(&self, transport: Transport, records: u64) {
        let c = self.of(transport);
        c.records.fetch_add(records, Ordering::Relaxed);
        c.batches.fetch_add(1, Ordering::Relaxed);
    }

    pub fn totals(&self) -> IngestTotals {
        let get = |a: &AtomicU64| a.load(Ordering::Relaxed);
        IngestTotals {
            grpc_records: get(&self.grpc.records),
            grpc_batches: get(&self.grpc.batches),
            shm_records: get(&self.shm.records),
            shm_batches: get(&self.shm.batches),
            shm_lost_records: get(&self.shm.lost_records),
            refused_batches: get(&self.grpc.refused_batches) + get(&self.shm.refused_batches),
            unused_records: get(&self.unused_records),
        }
    }
}

impl std::fmt::Display for IngestTotals {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "ingest_records_total{{transport=\"shm\"}}={} ingest_records_total{{transport=\"grpc\"}}={} \
             (batches shm {} grpc {}); shm lost records {}; refused batches {}; \
             unused at the stop {}",
            self.shm_records,
            self.grpc_records,
            self.shm_batches,
            self.grpc_batches,
            self.shm_lost_records,
            self.refused_batches,
            self.unused_records
        )
    }
}

/// Per-stream counts, shared by the `PushTransitions` handler and the training thread.
#[derive(Debug)]
pub struct StreamTally {
    /// The learner's totals, where this stream's unused records are counted too.
    counters: Arc<IngestCounters>,
    /// Records stored in the replay.
    pub accepted: AtomicU64,
    /// Records dropped because their stage epoch had ended (spec 4).
    pub dropped_stale_epoch: AtomicU64,
    /// Records not used because the run stopped (budget reached, shutdown).
    pub discarded: AtomicU64,
    /// Batches handed back (handled or discarded).
    finished: watch::Sender<u64>,
}

impl StreamTally {
    pub fn new(counters: Arc<IngestCounters>) -> Arc<Self> {
        Arc::new(Self {
            counters,
            accepted: AtomicU64::new(0),
            dropped_stale_epoch: AtomicU64::new(0),
            discarded: AtomicU64::new(0),
            finished: watch::channel(0).0,
        })
    }

    /// Waits until `batches` batches of this stream were handed back.
    pub async fn wait_finished(&self, batches: u64) {
        let mut rx = self.finished.subscribe();
        // The sender lives in `self`, so this cannot fail while we wait.
        let _ = rx.wait_for(|&done| done >= batches).await;
    }

    pub fn summary(&self) -> v1::PushSummary {
        v1::PushSummary {
            accepted: self.accepted.load(Ordering::Relaxed),
            dropped_stale_epoch: self.dropped_stale_epoch.load(Ordering::Relaxed),
        }
    }
}

/// One validated batch on its way to the training thread. Dropping it (handled, or discarded
/// with the queue at shutdown) tells its stream.
#[derive(Debug)]
pub struct IngestItem {
    pub layout: RecordLayout,
    pub records: Vec<u8>,
    pub count: usize,
    /// Records of this item already handled by the training thread.
    pub next: usize,
    pub tally: Arc<StreamTally>,
}

impl IngestItem {
    pub fn new(
        layout: RecordLayout,
        records: Vec<u8>,
        count: usize,
        tally: Arc<StreamTally>,
    ) -> Self {
        Self {
            layout,
            records,
            count,
            next: 0,
            tally,
        }
    }

    /// Record `i` (validated at the edge).
    pub fn record(&self, i: usize) -> RecordView<'_> {
        let n = self.layout.record_bytes();
        self.layout
            .view(&self.records[i * n..(i + 1) * n])
            .expect("records were validated at the edge")
    }

    /// Records not handled yet.
    pub fn remaining(&self) -> usize {
        self.count - self.next
    }
}

impl Drop for IngestItem {
    fn drop(&mut self) {
        let left = self.remaining() as u64;
        if left > 0 {
            self.tally.discarded.fetch_add(left, Ordering::Relaxed);
            self.tally
                .counters
                .unused_records
                .fetch_add(left, Ordering::Relaxed);
        }
        self.tally.finished.send_modify(|n| *n += 1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rfcl_core::transition::Transition;

    fn transition(obs_dim: usize, action: Vec<f32>) -> Transition {
        Transition {
            obs: vec![0.5; obs_dim],
            action,
            reward: 1.0,
            next_obs: vec![0.25; obs_dim],
            mask: 1.0,
            stage_epoch: 0,
            actor_id: 3,
            policy_version: 7,
        }
    }

    fn batch(layout: RecordLayout, ts: &[Transition]) -> v1::TransitionBatch {
        let mut records = vec![0; ts.len() * layout.record_bytes()];
        layout.encode_batch(ts, &mut records).unwrap();
        v1::TransitionBatch {
            actor_id: 3,
            obs_dim: layout.obs_dim as u32,
            action_dim: layout.action_dim as u32,
            count: ts.len() as u32,
            records,
        }
    }

    #[test]
    fn a_valid_batch_passes_with_its_oldest_policy_version() {
        let layout = RecordLayout::new(3, 2);
        let mut ts = vec![
            transition(3, vec![0.5, -1.0]),
            transition(3, vec![1.0, 0.0]),
        ];
        ts[1].policy_version = 4;
        let info = validate_batch(&batch(layout, &ts), layout, 0).unwrap();
        assert_eq!(
            info,
            BatchInfo {
                count: 2,
                min_policy_version: 4
            }
        );
    }

    #[test]
    fn malformed_batches_name_the_field() {
        let layout = RecordLayout::new(3, 2);
        let good = batch(layout, &[transition(3, vec![0.0, 0.0])]);
        let field = |b: &v1::TransitionBatch| validate_batch(b, layout, 1).unwrap_err();

        let wrong_obs = v1::TransitionBatch {
            obs_dim: 4,
            ..good.clone()
        };
        assert_eq!(field(&wrong_obs).field, "obs_dim");
        let wrong_action = v1::TransitionBatch {
            action_dim: 1,
            ..good.clone()
        };
        assert_eq!(field(&wrong_action).field, "action_dim");
        let wrong_count = v1::TransitionBatch {
            count: 2,
            ..good.clone()
        };
        let e = field(&wrong_count);
        assert_eq!(e.field, "records");
        assert!(e.to_string().contains("TransitionBatch.records"), "{e}");

        let mut nan = transition(3, vec![0.0, 0.0]);
        nan.next_obs[2] = f32::NAN;
        let e = field(&batch(layout, &[transition(3, vec![0.0, 0.0]), nan]));
        assert!(e.problem.contains("record 1: next_obs[2]"), "{e}");
        let e = field(&batch(layout, &[transition(3, vec![0.0, 1.5])]));
        assert!(e.problem.contains("action[1] = 1.5"), "{e}");
        let mut mask = transition(3, vec![0.0, 0.0]);
        mask.mask = 0.5;
        assert!(field(&batch(layout, &[mask])).problem.contains("mask"));
        let mut ahead = transition(3, vec![0.0, 0.0]);
        ahead.stage_epoch = 2;
        let e = field(&batch(layout, &[ahead]));
        assert!(e.problem.contains("stage_epoch 2 is ahead"), "{e}");
        let status: tonic::Status = field(&wrong_obs).into();
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
    }

    #[test]
    fn transports_are_counted_apart() {
        let c = IngestCounters::new();
        c.queued(Transport::Shm, 64);
        c.queued(Transport::Shm, 10);
        c.queued(Transport::Grpc, 5);
        c.shm.lost_records.fetch_add(3, Ordering::Relaxed);
        c.grpc.refused_batches.fetch_add(1, Ordering::Relaxed);
        let t = c.totals();
        assert_eq!((t.shm_records, t.shm_batches), (74, 2));
        assert_eq!((t.grpc_records, t.grpc_batches), (5, 1));
        assert_eq!((t.shm_lost_records, t.refused_batches), (3, 1));
        assert!(t
            .to_string()
            .contains("ingest_records_total{transport=\"shm\"}=74"));
    }

    #[test]
    fn both_transports_refuse_the_same_records() {
        let layout = RecordLayout::new(3, 2);
        let b = batch(layout, &[transition(3, vec![0.0, 2.0])]);
        let header = RecordsHeader {
            obs_dim: 3,
            action_dim: 2,
            count: 1,
        };
        let grpc = validate_batch(&b, layout, 0).unwrap_err();
        let shm = validate_records("shm frame", header, &b.records, layout, 0).unwrap_err();
        assert_eq!((grpc.field, &grpc.problem), (shm.field, &shm.problem));
        assert!(
            shm.to_string().starts_with("malformed shm frame.records"),
            "{shm}"
        );
    }

    #[tokio::test]
    async fn dropping_items_finishes_them_and_counts_the_unused_records() {
        let layout = RecordLayout::new(3, 2);
        let counters = IngestCounters::new();
        let tally = StreamTally::new(counters.clone());
        let records = batch(layout, &vec![transition(3, vec![0.0, 0.0]); 4]).records;
        let mut item = IngestItem::new(layout, records.clone(), 4, tally.clone());
        assert_eq!(item.record(3).actor_id(), 3);
        item.next = 3;
        drop(item);
        drop(IngestItem::new(layout, records, 4, tally.clone()));
        tally.wait_finished(2).await;
        // 1 left of the first item, 4 of the second: in the stream's tally and the totals.
        assert_eq!(tally.discarded.load(Ordering::Relaxed), 5);
        assert_eq!(counters.totals().unused_records, 5);
    }
}
