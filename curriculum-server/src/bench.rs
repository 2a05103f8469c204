//! Load generator for `rfcl bench curriculum`: many concurrent actors doing Acquire + Report pairs
//! against a running curriculum server over real gRPC, with throughput and latency percentiles.
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rfcl_proto::auth::ClientAuth;
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

/// Runs `clients` concurrent clients (one connection each) for `duration`. Each acquires a lease,
/// then loops ReportAndAcquire (an actor's steady state: report the finished episode, get the next
/// lease) with a random outcome (success more likely near the end of a demo, so the curriculum
/// moves). A refused report (e.g. of a stage-1 lease after the stage changed) is counted as an error
/// and followed by a plain Acquire. Latency is that of one Report + Acquire pair.
pub async fn acquire_report(
    addr: &str,
    auth: &ClientAuth,
    clients: usize,
    duration: Duration,
) -> anyhow::Result<AcquireReportResult> {
    let mut conns = Vec::with_capacity(clients);
    for _ in 0..clients {
        let endpoint = auth.endpoint(tonic::transport::Endpoint::from_shared(addr.to_string())?)?;
        conns.push(CurriculumClient::new(auth.wrap(endpoint.connect().await?)));
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
                let next = v1::AcquireRequest {
                    actor_id: i as u32,
                    env_index: 0,
                    eval: false,
                };
                let mut lease = client.acquire(next).await?.into_inner();
                while Instant::now() < deadline {
                    let t0 = Instant::now();
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
                        actor_sim_restarts: 0,
                        reset_failure: String::new(),
                    };
                    let request = v1::ReportAndAcquireRequest {
                        report: Some(report),
                        next: Some(next),
                    };
                    match client.report_and_acquire(request).await {
                        Ok(reply) => {
                            lat_us.push(t0.elapsed().as_micros().min(u32::MAX as u128) as u32);
                            lease = reply
                                .into_inner()
                                .lease
                                .ok_or_else(|| anyhow::anyhow!("a reply without a lease"))?;
                        }
                        Err(_) => {
                            errors += 1;
                            lease = client.acquire(next).await?.into_inner();
                        }
                    }
                }
                anyhow::Ok((lat_us, errors))
            })
        })
        .collect();
    let mut all = Vec::new();
    let mut errors = 0;
    for t in tasks {
        let (lat, e) = t.await??;
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
