//! The learner binary's shared-memory transport, with real processes and real `/dev/shm`: this
//! test process publishes transition frames over iceoryx2 while a gRPC stream pushes others, and
//! subscribes to the policy service as a same-host actor would.
//!
//! It shows: the run description offers the run's services and recommends shared memory to a
//! process on the learner's host only; both transports feed the one ingest path (per-transport
//! counts match what was sent, nothing lost, under a burst many times the queues' size, with the
//! `sync` limiter holding the publisher back); policy versions over shared memory only grow, are
//! whole and carry the same bytes as WatchPolicy's; a malformed frame is refused and counted, as
//! gRPC refuses a malformed batch.
mod service_support;

use std::time::Duration;

use rfcl_policy::PolicyNet;
use rfcl_proto::v1;
use rfcl_shm::{PolicySubscriber, Sent, ShmNode, TransitionPublisher};
use service_support::*;

/// Warm-up of this test (as in service_grpc.rs).
const W: u64 = 8;
/// Records sent over shared memory, in frames of 6: 100 frames, against a service queue of 2
/// frames and an ingest queue of 2 batches.
const SHM_RECORDS: u64 = 600;
const GRPC_RECORDS: u64 = 48;

/// Sends `batches` over shared memory as an actor does (a frame that reached no subscriber is
/// sent again).
fn publish(publisher: &mut TransitionPublisher, batches: &[v1::TransitionBatch]) {
    for b in batches {
        while publisher
            .send(b.actor_id, b.obs_dim, b.action_dim, b.count, &b.records)
            .unwrap()
            == Sent::NoSubscriber
        {
            std::thread::sleep(Duration::from_millis(1));
        }
    }
}

fn record_bytes() -> usize {
    rfcl_core::transition::RecordLayout::new(OBS, ACT).record_bytes()
}

/// The policy versions received over shared memory.
#[derive(Default)]
struct Versions {
    seen: Vec<u64>,
    last_bytes: Vec<u8>,
    net: Option<PolicyNet>,
}

impl Versions {
    /// Takes the newest version if there is one: it must be newer than the last, and whole (it
    /// loads as the run's actor network).
    fn take(&mut self, policy: &PolicySubscriber, cfg: &rfcl_core::config::RunConfig) {
        let Some(frame) = policy.latest().unwrap() else {
            return;
        };
        let (header, weights) = frame.decode().unwrap();
        if let Some(&last) = self.seen.last() {
            assert!(header.version > last, "{} after {last}", header.version);
        }
        self.seen.push(header.version);
        match self.net.as_ref() {
            Some(net) => net.load(weights).unwrap(),
            None => self.net = Some(PolicyNet::from_safetensors(weights, cfg, OBS, ACT).unwrap()),
        }
        self.last_bytes = weights.to_vec();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shared_memory_and_grpc_feed_one_ingest_and_policies_arrive_whole() {
    let dir = tempfile::tempdir().unwrap();
    let pair = start_sync_pair(dir.path(), W);
    let mut client = pair.learner.client().await;

    // A process on another host is told gRPC; one on this host shared memory, with the services.
    let run_info = |host: String| v1::GetRunInfoRequest {
        actor_id: 1,
        hostname: "test".into(),
        host_identity: host,
    };
    let remote = client
        .get_run_info(run_info("machine-id=elsewhere".into()))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(remote.transport, "grpc");
    let info = client
        .get_run_info(run_info(rfcl_shm::host_identity()))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(info.transport, "shm");
    assert_eq!(info.learner_host_identity, rfcl_shm::host_identity());
    assert_eq!(info.run_id.len(), 16);
    let base = format!("rfcl/ltest/{}/", info.run_id);
    assert_eq!(info.shm_transitions_service, format!("{base}transitions"));
    assert_eq!(info.shm_policy_service, format!("{base}policy"));
    assert_eq!(remote.shm_policy_service, info.shm_policy_service);

    let (node, _) = ShmNode::create("ltest", "test-policy").unwrap();
    let policy = PolicySubscriber::open(node, &info.shm_policy_service).unwrap();
    let (node, _) = ShmNode::create("ltest", "test-transitions").unwrap();
    let mut publisher =
        TransitionPublisher::open(node, &info.shm_transitions_service, 6, record_bytes()).unwrap();

    // A new subscriber gets the current version (the initial one) from the service's history.
    let cfg = rfcl_core::config::resolve_file(&pair.config, &[]).unwrap();
    let mut versions = Versions::default();
    while versions.seen.is_empty() {
        versions.take(&policy, &cfg);
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    assert_eq!(versions.seen, [1]);

    // The burst over shared memory from a thread (it blocks while the learner holds it back),
    // a gRPC stream at the same time.
    let shm_batches = batches(0..SHM_RECORDS, 6, 0);
    let sender = std::thread::spawn(move || {
        publish(&mut publisher, &shm_batches);
        publisher
    });
    let grpc_batches = batches(SHM_RECORDS..SHM_RECORDS + GRPC_RECORDS, 8, 0);
    let mut pusher = pair.learner.client().await;
    let pushed = tokio::spawn(async move { push(&mut pusher, grpc_batches).await });

    // Policies as a same-host actor sees them, while the sync limiter holds the data back: the
    // iterations never fall behind the schedule, whichever transport brought the steps.
    let total = SHM_RECORDS + GRPC_RECORDS;
    let final_health = loop {
        versions.take(&policy, &cfg);
        let h = health(&mut client).await;
        let (iterations, owed) = (h.updates / G, earned(h.env_steps, W));
        assert!(
            iterations == owed || iterations + 1 == owed,
            "{iterations} iterations at {} env steps, the schedule owes {owed}",
            h.env_steps
        );
        if h.env_steps == total && iterations == owed && h.policy_version == owed + 1 {
            break h;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    };
    let summary = pushed.await.unwrap().unwrap();
    assert_eq!(summary.accepted, GRPC_RECORDS);
    let mut publisher = sender.join().unwrap();
    assert_eq!(publisher.frames_sent(), SHM_RECORDS / 6);

    // The learner's own counters: every record in, per transport, none lost or refused.
    assert_eq!(final_health.shm_records, SHM_RECORDS, "{final_health:?}");
    assert_eq!(final_health.shm_batches, SHM_RECORDS / 6);
    assert_eq!(final_health.grpc_records, GRPC_RECORDS);
    assert_eq!(final_health.grpc_batches, GRPC_RECORDS / 8);
    assert_eq!(
        (final_health.shm_lost_records, final_health.refused_batches),
        (0, 0)
    );

    // The newest version over shared memory is WatchPolicy's, byte for byte.
    let last = final_health.policy_version;
    while versions.seen.last() != Some(&last) {
        versions.take(&policy, &cfg);
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let mut watch = client
        .watch_policy(v1::WatchPolicyRequest {
            after_version: last - 1,
        })
        .await
        .unwrap()
        .into_inner();
    let grpc_last = watch.message().await.unwrap().unwrap();
    assert_eq!(grpc_last.version, last);
    assert_eq!(&versions.last_bytes[..], &grpc_last.safetensors[..]);

    // A malformed frame is refused and counted; the frames after it still count.
    let mut bad = batches(0..1, 1, 0).remove(0);
    bad.obs_dim += 1;
    publish(&mut publisher, &[bad]);
    let h = wait_health(&mut client, Duration::from_secs(60), |h| {
        h.refused_batches == 1
    })
    .await;
    assert_eq!(h.shm_records, SHM_RECORDS);
}
