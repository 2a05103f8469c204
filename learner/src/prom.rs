//! Prometheus `/metrics` of the learner (`learner --metrics-port P`): `rfcl_learner_*` gauges and
//! counters for what an operator watches live (where the time goes, whether memory
//! keeps growing): updates/s, achieved UTD, buffer fill and bytes, dropped records
//! by reason, policy version and lag, where the time went, RSS.
//!
//! The training thread copies its counters into one [`Snapshot`] at the consistent points where
//! it also updates the gRPC Health status; a scrape encodes that snapshot (a [`Collector`]), so
//! every scrape shows one moment and the training thread never formats text. Totals count from
//! the start of the run (a resumed learner starts from its checkpoint's counters); rates are
//! over the last progress window (10 s, [`crate::trainer::REPORT_EVERY`]).
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::registry::Registry;

use crate::metrics::Timings;

/// Prefix of every metric name.
pub const PREFIX: &str = "rfcl_learner";

/// Fill of one replay buffer.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct BufferStats {
    pub len: usize,
    pub capacity: usize,
    /// Bytes allocated for the buffer (capacity × record size).
    pub bytes: usize,
}

/// One consistent reading of the training thread's state.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Snapshot {
    pub env_steps: u64,
    pub critic_updates: u64,
    pub actor_updates: u64,
    pub iterations: u64,
    /// Critic updates / env steps per second over the last progress window.
    pub updates_per_s: f64,
    pub env_steps_per_s: f64,
    pub utd: f64,
    pub utd_target: f64,
    pub online: BufferStats,
    /// `None` without an offline buffer.
    pub offline: Option<BufferStats>,
    pub stage: u32,
    pub stage_epoch: u64,
    pub policy_version: u64,
    /// Largest policy lag (learner version − the record's) over the last progress window.
    pub policy_lag_max: u64,
    pub dropped_stale_epoch: u64,
    /// Records received but never used because the run ended.
    pub unused_at_end: u64,
    /// Seconds per activity since this process started.
    pub seconds: Timings,
}

/// The learner's Prometheus state: the latest [`Snapshot`] and drop counts reported by the
/// transports. Cheap to update; shared as `Arc` between the training thread, the ingest and the
/// HTTP server.
#[derive(Debug, Default)]
pub struct LearnerMetrics {
    snapshot: Mutex<Snapshot>,
    /// Records dropped before they reached the training thread, by reason (from the ingest).
    ingest_drops: Mutex<BTreeMap<&'static str, u64>>,
    /// More metrics encoded on each scrape (e.g. the transports' own counters).
    extra: Mutex<Vec<Arc<dyn Collector>>>,
}

/// An `Arc<dyn Collector>` as a `Collector` (prometheus-client implements it for `Arc<T>` with a
/// sized `T` only).
#[derive(Debug)]
struct Shared(Arc<dyn Collector>);

impl Collector for Shared {
    fn encode(&self, encoder: DescriptorEncoder) -> std::fmt::Result {
        self.0.encode(encoder)
    }
}

impl LearnerMetrics {
    pub fn set(&self, snapshot: Snapshot) {
        *self.snapshot.lock().unwrap_or_else(|p| p.into_inner()) = snapshot;
    }

    pub fn snapshot(&self) -> Snapshot {
        self.snapshot
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Counts `n` records dropped by a transport for `reason` (a short snake_case word, e.g.
    /// `invalid`); shown as `rfcl_learner_dropped_records_total{reason="..."}`.
    pub fn count_drop(&self, reason: &'static str, n: u64) {
        *self
            .ingest_drops
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .entry(reason)
            .or_default() += n;
    }

    /// Every drop reason with its count: the training thread's and the transports'.
    pub fn drops(&self) -> BTreeMap<&'static str, u64> {
        let s = self.snapshot();
        let mut drops = self
            .ingest_drops
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        *drops.entry("stale_epoch").or_default() += s.dropped_stale_epoch;
        *drops.entry("unused_at_end").or_default() += s.unused_at_end;
        drops
    }

    /// Adds metrics of another part of the learner to every scrape; their names get the
    /// `rfcl_learner_` prefix.
    pub fn add_collector(&self, collector: Arc<dyn Collector>) {
        self.extra
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(collector);
    }

    /// The exposition text (what `/metrics` answers).
    pub fn encode(self: &Arc<Self>) -> String {
        let mut registry = Registry::with_prefix(PREFIX);
        registry.register_collector(Box::new(self.clone()));
        for c in self.extra.lock().unwrap_or_else(|p| p.into_inner()).iter() {
            registry.register_collector(Box::new(Shared(c.clone())));
        }
        let mut out = String::new();
        prometheus_client::encoding::text::encode(&mut out, &registry)
            .expect("writing to a String cannot fail");
        out
    }
}

/// Resident set size of this process in bytes (`VmRSS` of `/proc/self/status`), if readable.
pub fn resident_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// One metric without labels; its type is the metric's.
fn metric(
    e: &mut DescriptorEncoder,
    name: &str,
    help: &str,
    value: impl EncodeMetric,
) -> std::fmt::Result {
    value.encode(e.encode_descriptor(name, help, None, value.metric_type())?)
}

/// A family of `make(value)` with one label; its type is the metric's (asked of
/// `make(N::default())`, so that an empty family still has its descriptor).
fn family<N: Copy + Default, M: EncodeMetric>(
    e: &mut DescriptorEncoder,
    name: &str,
    help: &str,
    label: &str,
    values: &[(&str, N)],
    make: impl Fn(N) -> M,
) -> std::fmt::Result {
    let kind = make(N::default()).metric_type();
    let mut m = e.encode_descriptor(name, help, None, kind)?;
    for (value_of_label, v) in values {
        let labels = [(label, *value_of_label)];
        make(*v).encode(m.encode_family(&labels)?)?;
    }
    Ok(())
}

impl Collector for LearnerMetrics {
    fn encode(&self, mut e: DescriptorEncoder) -> std::fmt::Result {
        let s = self.snapshot();
        let e = &mut e;
        metric(
            e,
            "env_steps",
            "Env steps (transitions) stored",
            ConstCounter::new(s.env_steps),
        )?;
        metric(
            e,
            "critic_updates",
            "Critic updates",
            ConstCounter::new(s.critic_updates),
        )?;
        metric(
            e,
            "actor_updates",
            "Actor (and temperature) updates",
            ConstCounter::new(s.actor_updates),
        )?;
        metric(
            e,
            "iterations",
            "Training iterations (docs/ALGORITHM.md 5.2)",
            ConstCounter::new(s.iterations),
        )?;
        metric(
            e,
            "updates_per_second",
            "Critic updates per second over the last progress window",
            ConstGauge::new(s.updates_per_s),
        )?;
        metric(
            e,
            "env_steps_per_second",
            "Env steps stored per second over the last progress window",
            ConstGauge::new(s.env_steps_per_s),
        )?;
        metric(
            e,
            "utd",
            "Achieved critic updates per env step",
            ConstGauge::new(s.utd),
        )?;
        metric(
            e,
            "utd_target",
            "Configured critic updates per env step (G/K)",
            ConstGauge::new(s.utd_target),
        )?;
        let buffers: Vec<(&str, BufferStats)> = std::iter::once(("online", s.online))
            .chain(s.offline.map(|b| ("offline", b)))
            .collect();
        type Stat = fn(&BufferStats) -> i64;
        let replay: [(&str, &str, Stat); 3] = [
            (
                "replay_transitions",
                "Transitions stored per replay buffer",
                |b| b.len as i64,
            ),
            (
                "replay_capacity",
                "Capacity in transitions per replay buffer",
                |b| b.capacity as i64,
            ),
            ("replay_bytes", "Bytes allocated per replay buffer", |b| {
                b.bytes as i64
            }),
        ];
        for (name, help, stat) in replay {
            let values: Vec<(&str, i64)> = buffers.iter().map(|(n, b)| (*n, stat(b))).collect();
            family(e, name, help, "buffer", &values, ConstGauge::new)?;
        }
        let drops: Vec<(&str, u64)> = self.drops().into_iter().collect();
        family(
            e,
            "dropped_records",
            "Transition records dropped, by reason",
            "reason",
            &drops,
            ConstCounter::new,
        )?;
        metric(
            e,
            "policy_version",
            "Latest published policy version",
            ConstGauge::new(s.policy_version),
        )?;
        metric(
            e,
            "policy_lag_max",
            "Largest policy lag of a stored record over the last progress window (versions)",
            ConstGauge::new(s.policy_lag_max),
        )?;
        metric(
            e,
            "stage",
            "Curriculum stage (1 or 2)",
            ConstGauge::new(s.stage),
        )?;
        metric(
            e,
            "stage_epoch",
            "Stage epoch",
            ConstGauge::new(s.stage_epoch),
        )?;
        let t = s.seconds;
        family(
            e,
            "time_seconds",
            "Seconds the training thread spent per activity",
            "activity",
            &[
                ("wait", t.wait),
                ("ingest", t.ingest),
                ("update", t.update),
                ("publish", t.publish),
                ("checkpoint", t.checkpoint),
            ],
            ConstCounter::new,
        )?;
        if let Some(rss) = resident_bytes() {
            metric(
                e,
                "resident_memory_bytes",
                "Resident set size of the learner process",
                ConstGauge::new(rss),
            )?;
        }
        Ok(())
    }
}

/// The transports' counters (`learner/src/ingest.rs`) on `/metrics`:
/// `rfcl_learner_ingest_{records,batches,refused_batches,lost_records}_total{transport}`.
/// Register with `metrics.add_collector(counters.clone())`.
impl Collector for crate::ingest::IngestCounters {
    fn encode(&self, mut e: DescriptorEncoder) -> std::fmt::Result {
        use crate::ingest::{Transport, TransportCounts};
        use std::sync::atomic::{AtomicU64, Ordering};
        type Pick = fn(&TransportCounts) -> &AtomicU64;
        let fields: [(&str, &str, Pick); 4] = [
            (
                "ingest_records",
                "Transition records validated and queued, per transport",
                |c| &c.records,
            ),
            (
                "ingest_batches",
                "Transition batches validated and queued, per transport",
                |c| &c.batches,
            ),
            (
                "ingest_refused_batches",
                "Malformed transition batches refused, per transport",
                |c| &c.refused_batches,
            ),
            (
                "ingest_lost_records",
                "Transition records missing between one sender's batches, per transport",
                |c| &c.lost_records,
            ),
        ];
        for (name, help, pick) in fields {
            let values: Vec<(&str, u64)> = [Transport::Grpc, Transport::Shm]
                .into_iter()
                .map(|t| (t.as_str(), pick(self.of(t)).load(Ordering::Relaxed)))
                .collect();
            family(&mut e, name, help, "transport", &values, ConstCounter::new)?;
        }
        Ok(())
    }
}

/// The gRPC service's token check on `/metrics`: `rfcl_learner_unauthenticated_calls_total`.
/// Register with `metrics.add_collector(Arc::new(Unauthenticated(guard.clone())))`.
#[derive(Debug)]
pub struct Unauthenticated(pub rfcl_proto::auth::Guard);

impl Collector for Unauthenticated {
    fn encode(&self, mut e: DescriptorEncoder) -> std::fmt::Result {
        metric(
            &mut e,
            "unauthenticated_calls",
            "gRPC calls refused for a missing or wrong run token",
            ConstCounter::new(self.0.refused()),
        )
    }
}

/// Serves `GET /metrics` on `listener` until `shutdown` resolves.
pub async fn serve(
    listener: tokio::net::TcpListener,
    metrics: Arc<LearnerMetrics>,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    use axum::http::header::CONTENT_TYPE;
    let app = axum::Router::new().route(
        "/metrics",
        axum::routing::get(move || {
            let metrics = metrics.clone();
            async move {
                (
                    [(
                        CONTENT_TYPE,
                        "application/openmetrics-text; version=1.0.0; charset=utf-8",
                    )],
                    metrics.encode(),
                )
            }
        }),
    );
    axum::serve(listener, app)
        .with_graceful_shutdown(shutdown)
        .await
}

/// The address a metrics listener is bound to, for the ready line.
pub fn describe(addr: SocketAddr) -> String {
    format!("http://{addr}/metrics")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposition_has_every_metric_with_rfcl_learner_names() {
        let metrics = Arc::new(LearnerMetrics::default());
        metrics.set(Snapshot {
            env_steps: 1200,
            critic_updates: 480,
            updates_per_s: 52.5,
            utd: 0.4,
            utd_target: 0.5,
            online: BufferStats {
                len: 1200,
                capacity: 10_000,
                bytes: 4_000_000,
            },
            offline: Some(BufferStats {
                len: 300,
                capacity: 300,
                bytes: 120_000,
            }),
            policy_version: 31,
            dropped_stale_epoch: 7,
            seconds: Timings {
                update: 2.5,
                ..Timings::default()
            },
            ..Snapshot::default()
        });
        metrics.count_drop("invalid", 3);
        metrics.count_drop("invalid", 2);
        #[derive(Debug)]
        struct Extra;
        impl Collector for Extra {
            fn encode(&self, mut e: DescriptorEncoder) -> std::fmt::Result {
                metric(&mut e, "ingest_batches", "Batches", ConstCounter::new(9u64))
            }
        }
        metrics.add_collector(Arc::new(Extra));
        let text = metrics.encode();
        for line in [
            "rfcl_learner_env_steps_total 1200",
            "rfcl_learner_critic_updates_total 480",
            "rfcl_learner_updates_per_second 52.5",
            "rfcl_learner_utd 0.4",
            "rfcl_learner_utd_target 0.5",
            "rfcl_learner_replay_transitions{buffer=\"online\"} 1200",
            "rfcl_learner_replay_transitions{buffer=\"offline\"} 300",
            "rfcl_learner_replay_capacity{buffer=\"online\"} 10000",
            "rfcl_learner_replay_bytes{buffer=\"online\"} 4000000",
            "rfcl_learner_dropped_records_total{reason=\"stale_epoch\"} 7",
            "rfcl_learner_dropped_records_total{reason=\"invalid\"} 5",
            "rfcl_learner_dropped_records_total{reason=\"unused_at_end\"} 0",
            "rfcl_learner_policy_version 31",
            "rfcl_learner_time_seconds_total{activity=\"update\"} 2.5",
            "rfcl_learner_time_seconds_total{activity=\"wait\"} 0.0",
            "rfcl_learner_ingest_batches_total 9",
        ] {
            assert!(
                text.lines().any(|l| l == line),
                "missing {line:?} in:\n{text}"
            );
        }
        assert!(text.contains("# TYPE rfcl_learner_resident_memory_bytes gauge"));
        assert!(text.trim_end().ends_with("# EOF"));
    }

    #[test]
    fn ingest_counters_are_exposed_per_transport() {
        let metrics = Arc::new(LearnerMetrics::default());
        let counters = crate::ingest::IngestCounters::new();
        counters.queued(crate::ingest::Transport::Shm, 64);
        metrics.add_collector(counters.clone());
        let text = metrics.encode();
        for line in [
            "rfcl_learner_ingest_records_total{transport=\"shm\"} 64",
            "rfcl_learner_ingest_batches_total{transport=\"shm\"} 1",
            "rfcl_learner_ingest_records_total{transport=\"grpc\"} 0",
            "rfcl_learner_ingest_lost_records_total{transport=\"grpc\"} 0",
        ] {
            assert!(
                text.lines().any(|l| l == line),
                "missing {line:?} in:\n{text}"
            );
        }
    }

    #[test]
    fn resident_memory_is_read_from_proc() {
        let rss = resident_bytes().expect("/proc/self/status has VmRSS on Linux");
        assert!(rss > 1 << 20, "RSS {rss} B");
    }
}
