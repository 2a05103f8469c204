//! Load generator for `rfcl bench curriculum`: many concurrent actors doing Acquire + Report pairs
//! against a running curriculum server over real gRPC, with throughput and latency percentiles.
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rfcl_proto::v1::{self, curriculum_client::CurriculumClient};
use serde::Serialize;

#[derive(Debug, Clone, Serialize)]
pub struct AcquireReportResult {
    pub clients: usize,
    pub seconds: f64,
    pub pairs: u64,
    pub pairs_per_s: f64,
    pub p50_ms: f64,
    pub p90_ms: f64,
    pub p99_ms: f64,
    pub max_ms: f64,
    pub errors: u64,
}

/// Runs `clients` concurrent clients (one connection each) for `duration`; each loops Acquire, then
/// Report with a random outcome (success more likely near the end of a demo, so the curriculum
/// moves). Latency is that of one Acquire + Report pair.
pub async fn acquire_report(
    addr: &str,
    clients: usize,
    duration: Duration,
) -> anyhow::Result<AcquireReportResult> {
    let mut conns = Vec::with_capacity(clients);
    for _ in 0..clients {
        conns.push(CurriculumClient::connect(addr.to_string()).await?);
    }
    let start = Instant::now();
    let deadline = start + duration;
    let tasks: Vec<_> = conns
        .into_iter()
        .enumerate()
        .map(|(i, mut client)| {
            tokio::spawn(async move {
                let mut rng = ChaCha8Rng::seed_from_u64(i as u64);
                let mut lat_us: Vec<u32> = Vec::with_capacity(1 << 16);
                let mut errors = 0u64;
                while Instant::now() < deadline {
                    let t0 = Instant::now();
                    let req = v1::AcquireRequest {
                        actor_id: i as u32,
                        env_index: 0,
                        eval: false,
                    };
                    let lease = match client.acquire(req).await {
                        Ok(l) => l.into_inner(),
                        Err(_) => {
                            errors += 1;
                            continue;
                        }
                    };
                    let near_end =
                        lease.kind != v1::LeaseKind::DemoState as i32 || lease.time_limit <= 20;
                    let success = rng.random_bool(if near_end { 0.9 } else { 0.3 });
                    let report = v1::EpisodeReport {
                        lease_id: lease.lease_id,
                        success_at_end: success,
                        success_once: success,
                        episode_return: success as u8 as f64,
                        length: lease.time_limit,
                        policy_version: 0,
                        stage_epoch: lease.stage_epoch,
                        actor_id: i as u32,
                        actor_env_steps: 0,
                        policy_env_steps: 0,
                    };
                    if client.report(report).await.is_err() {
                        errors += 1;
                        continue;
                    }
                    lat_us.push(t0.elapsed().as_micros().min(u32::MAX as u128) as u32);
                }
                (lat_us, errors)
            })
        })
        .collect();
    let mut all = Vec::new();
    let mut errors = 0;
    for t in tasks {
        let (lat, e) = t.await?;
        all.extend(lat);
        errors += e;
    }
    let seconds = start.elapsed().as_secs_f64();
    all.sort_unstable();
    let pct = |p: f64| {
        if all.is_empty() {
            0.0
        } else {
            all[((all.len() - 1) as f64 * p).round() as usize] as f64 / 1000.0
        }
    };
    Ok(AcquireReportResult {
        clients,
        seconds,
        pairs: all.len() as u64,
        pairs_per_s: all.len() as f64 / seconds,
        p50_ms: pct(0.5),
        p90_ms: pct(0.9),
        p99_ms: pct(0.99),
        max_ms: pct(1.0),
        errors,
    })
}
