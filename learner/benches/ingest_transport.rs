//! `cargo bench -p rfcl-learner --bench ingest_transport`: transition records per second into the
//! learner's ingest queue over shared memory (iceoryx2) and over gRPC (`PushTransitions` on
//! loopback), side by side in one run, printed as JSON lines.
//!
//! Both paths are the learner's own code: [`ShmTransport`] and [`LearnerService`] with the same
//! validation and the same bounded queue; a consumer thread stands in for the training thread
//! (it takes each queued batch and drops it, so nothing but the transport and the checks is
//! measured). The sender is an actor's: 64-record batches of paper-size records (obs 42, action
//! 8: 400 B each), frames resent when no subscriber took them; gRPC as one long stream (the
//! transport's best case; actors use acknowledged windows of 2 batches, measured as
//! `grpc_windowed`).
//!
//! Environment: `RFCL_BENCH_SECONDS` (seconds per transport, default 3), `RFCL_BENCH_BATCH`
//! (records per batch, default 64).
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use rfcl_core::transition::{RecordLayout, Transition};
use rfcl_learner::ingest::{IngestCounters, IngestItem};
use rfcl_learner::service::{self, LearnerService, RunDescription};
use rfcl_learner::shm::{ShmSetup, ShmTransport};
use rfcl_learner::trainer::{LearnerStatus, PublishedPolicy};
use rfcl_proto::auth::{authenticated, ServerAuth, Token};
use rfcl_proto::v1;
use rfcl_proto::v1::learner_client::LearnerClient;
use rfcl_shm::{PolicyLimits, Sent, ShmNode, TransitionLimits, TransitionPublisher};
use tokio::sync::{mpsc, watch};

const OBS: usize = 42;
const ACT: usize = 8;

fn records(layout: RecordLayout, n: usize) -> Vec<u8> {
    let ts: Vec<Transition> = (0..n)
        .map(|i| Transition {
            obs: vec![0.25; OBS],
            action: vec![0.5; ACT],
            reward: (i % 2) as f32,
            next_obs: vec![0.75; OBS],
            mask: 1.0,
            stage_epoch: 0,
            actor_id: 1,
            policy_version: 1,
        })
        .collect();
    let mut out = vec![0; n * layout.record_bytes()];
    layout.encode_batch(&ts, &mut out).unwrap();
    out
}

/// Takes queued items like the training thread does (and drops them), counting records.
fn consumer(mut rx: mpsc::Receiver<IngestItem>) -> (Arc<AtomicU64>, std::thread::JoinHandle<()>) {
    let taken = Arc::new(AtomicU64::new(0));
    let t = taken.clone();
    let handle = std::thread::spawn(move || {
        while let Some(item) = rx.blocking_recv() {
            t.fetch_add(item.count as u64, Ordering::Relaxed);
        }
    });
    (taken, handle)
}

struct Measured {
    records: u64,
    seconds: f64,
}

fn report(transport: &str, batch: usize, layout: RecordLayout, m: &Measured) {
    let rate = m.records as f64 / m.seconds;
    println!(
        "{{\"bench\":\"ingest_transport\",\"transport\":\"{transport}\",\"batch\":{batch},\"record_bytes\":{},\"records\":{},\"seconds\":{:.3},\"records_per_s\":{:.0},\"mb_per_s\":{:.1}}}",
        layout.record_bytes(),
        m.records,
        m.seconds,
        rate,
        rate * layout.record_bytes() as f64 / 1e6
    );
}

fn policy_channel() -> (
    watch::Sender<Arc<PublishedPolicy>>,
    watch::Receiver<Arc<PublishedPolicy>>,
) {
    watch::channel(Arc::new(PublishedPolicy {
        version: 1,
        safetensors: vec![0u8; 1024].into(),
        learner_env_steps: 0,
    }))
}

fn bench_shm(
    rt: &tokio::runtime::Runtime,
    layout: RecordLayout,
    batch: usize,
    seconds: f64,
) -> Measured {
    let (data_tx, data_rx) = mpsc::channel(8);
    let (taken, consumer) = consumer(data_rx);
    let (_policy_tx, policy_rx) = policy_channel();
    let (stopping_tx, stopping_rx) = watch::channel(false);
    let run_id = rfcl_shm::new_run_id();
    let transport = ShmTransport::start(
        ShmSetup {
            run_name: "bench".into(),
            run_id,
            layout,
            policy_bytes: 1024,
            transitions: TransitionLimits::default(),
            policy: PolicyLimits::default(),
        },
        Arc::new(LearnerStatus::default()),
        data_tx,
        policy_rx,
        IngestCounters::new(),
        stopping_rx,
        rt.handle().clone(),
    )
    .expect("starting the shared-memory transport");
    let (node, _) = ShmNode::create("bench", "bench-actor").unwrap();
    let mut publisher = TransitionPublisher::open(
        node,
        &transport.names.transitions,
        batch,
        layout.record_bytes(),
    )
    .unwrap();
    let bytes = records(layout, batch);
    let start = Instant::now();
    let until = start + Duration::from_secs_f64(seconds);
    let mut sent = 0u64;
    while Instant::now() < until {
        match publisher
            .send(1, OBS as u32, ACT as u32, batch as u32, &bytes)
            .unwrap()
        {
            Sent::Delivered => sent += batch as u64,
            Sent::NoSubscriber => std::thread::yield_now(),
        }
    }
    while taken.load(Ordering::Relaxed) < sent {
        std::thread::yield_now();
    }
    let m = Measured {
        records: sent,
        seconds: start.elapsed().as_secs_f64(),
    };
    let _ = stopping_tx.send(true);
    drop(publisher);
    transport.join(Duration::from_secs(5));
    consumer.join().unwrap();
    m
}

fn bench_grpc(
    rt: &tokio::runtime::Runtime,
    layout: RecordLayout,
    batch: usize,
    seconds: f64,
    window: Option<usize>,
) -> Measured {
    let (data_tx, data_rx) = mpsc::channel(8);
    let (taken, consumer) = consumer(data_rx);
    let (_policy_tx, policy_rx) = policy_channel();
    let (stopping_tx, stopping_rx) = watch::channel(false);
    let token = Token::parse("bench-token-0123456789", "the bench").expect("a valid token");
    let auth = ServerAuth::plain(&token);
    let info = RunDescription {
        run_name: "bench".into(),
        env_id: "bench".into(),
        obs_dim: OBS as u32,
        action_dim: ACT as u32,
        curriculum_addr: String::new(),
        config_yaml: String::new(),
        run_seed: 0,
        learner_hostname: "bench".into(),
        run_id: "0".into(),
        host_identity: String::new(),
        shm: None,
        action_scale: None,
    };
    let service = LearnerService::new(
        info,
        Arc::new(LearnerStatus::default()),
        data_tx,
        policy_rx,
        stopping_rx.clone(),
        IngestCounters::new(),
        auth.guard.clone(),
    )
    .with_transition_batch(batch as u32);
    let measured = rt.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let mut stopped = stopping_rx.clone();
        let server = tokio::spawn(service::serve(listener, service, auth, async move {
            let _ = stopped.wait_for(|s| *s).await;
        }));
        let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
            .unwrap()
            .tcp_nodelay(true)
            .connect()
            .await
            .unwrap();
        let mut client = LearnerClient::new(authenticated(channel, &token));
        let message = v1::TransitionBatch {
            actor_id: 1,
            obs_dim: OBS as u32,
            action_dim: ACT as u32,
            count: batch as u32,
            records: records(layout, batch),
        };
        let start = Instant::now();
        let until = start + Duration::from_secs_f64(seconds);
        let mut sent = 0u64;
        match window {
            None => {
                let (tx, rx) = mpsc::channel::<v1::TransitionBatch>(4);
                let call = tokio::spawn({
                    let mut client = client.clone();
                    async move {
                        client
                            .push_transitions(tokio_stream::wrappers::ReceiverStream::new(rx))
                            .await
                    }
                });
                while Instant::now() < until {
                    tx.send(message.clone()).await.unwrap();
                    sent += batch as u64;
                }
                drop(tx);
                // The answer comes once every batch was taken.
                call.await.unwrap().unwrap();
            }
            Some(w) => {
                while Instant::now() < until {
                    let msgs = vec![message.clone(); w];
                    client
                        .push_transitions(tokio_stream::iter(msgs))
                        .await
                        .unwrap();
                    sent += (w * batch) as u64;
                }
            }
        }
        while taken.load(Ordering::Relaxed) < sent {
            tokio::task::yield_now().await;
        }
        let m = Measured {
            records: sent,
            seconds: start.elapsed().as_secs_f64(),
        };
        let _ = stopping_tx.send(true);
        let _ = server.await;
        m
    });
    consumer.join().unwrap();
    measured
}

fn main() {
    let seconds: f64 = std::env::var("RFCL_BENCH_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(3.0);
    let batch: usize = std::env::var("RFCL_BENCH_BATCH")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(64);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let layout = RecordLayout::new(OBS, ACT);
    let shm = bench_shm(&rt, layout, batch, seconds);
    report("shm", batch, layout, &shm);
    let grpc = bench_grpc(&rt, layout, batch, seconds, None);
    report("grpc_stream", batch, layout, &grpc);
    let windowed = bench_grpc(&rt, layout, batch, seconds, Some(2));
    report("grpc_windowed", batch, layout, &windowed);
    println!(
        "shared memory: {:.2}x the records/s of one gRPC stream, {:.2}x the actor's windowed gRPC",
        shm.records as f64 / shm.seconds / (grpc.records as f64 / grpc.seconds),
        shm.records as f64 / shm.seconds / (windowed.records as f64 / windowed.seconds)
    );
}
