//! The stage transition (spec 4) across real processes: the curriculum
//! server is driven to stage 2 by this test's own Acquire/Report calls; the learner then moves
//! its online buffer into the offline buffer, empties the online buffer, drops and counts late
//! records of the old epoch, and collects `sac.num_seed_steps` policy-only steps before it
//! updates again, keeping its optimiser states.
mod service_support;

use std::path::Path;
use std::time::Duration;

use rfcl_learner::checkpoint;
use rfcl_proto::auth::AuthChannel;
use rfcl_proto::v1::learner_client::LearnerClient;
use service_support::*;

const W: u64 = 8;

/// A run in a new temporary directory (W warm-up steps, a budget no test reaches, `train_keys`
/// added to its `train:` section) with its curriculum server and learner, and a learner client.
async fn start(train_keys: &str) -> (tempfile::TempDir, Pair, LearnerClient<AuthChannel>) {
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path(), W, 100_000, "");
    add_train_keys(&config, train_keys);
    let pair = Pair::start(dir.path(), config, &[]);
    let client = pair.learner.client().await;
    (dir, pair, client)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stage_2_moves_the_buffers_drops_late_records_and_warms_up_again() {
    let (_dir, mut pair, mut client) = start("").await;

    // Stage 1: 40 env steps, 8 iterations.
    push(&mut client, batches(0..40, 8, 0)).await.unwrap();
    wait_health(&mut client, Duration::from_secs(60), |h| {
        h.env_steps == 40 && h.updates == G * 8
    })
    .await;

    let epoch = pair.curriculum.drive_to_stage_2().await;
    assert_eq!(epoch, 1);

    // Records of the new epoch: accepted (after the learner applied the announcement), and the
    // W = 8 policy-only steps earn no update.
    let summary = push(&mut client, batches(40..48, 8, 1)).await.unwrap();
    assert_eq!((summary.accepted, summary.dropped_stale_epoch), (8, 0));
    // Late records of epoch 0: dropped and counted, exactly.
    let summary = push(&mut client, batches(0..10, 4, 0)).await.unwrap();
    assert_eq!((summary.accepted, summary.dropped_stale_epoch), (0, 10));
    let h = wait_health(&mut client, Duration::from_secs(30), |h| h.env_steps == 48).await;
    assert_eq!(
        h.updates,
        G * 8,
        "no update during stage 2's policy-only steps"
    );

    // 4 more steps: 12 steps into stage 2, the first stage-2 iteration is earned (spec 5.4).
    push(&mut client, batches(48..52, 4, 1)).await.unwrap();
    let h = wait_health(&mut client, Duration::from_secs(30), |h| h.updates == G * 9).await;
    assert_eq!((h.env_steps, h.policy_version), (52, 10));

    assert!(pair.learner.sigterm().success());
    let ckpt = checkpoint::checkpoint_dir(&pair.run_dir);
    let manifest = checkpoint::read_manifest(&ckpt).unwrap().unwrap();
    let p = &manifest.progress;
    assert_eq!((p.stage, p.stage_epoch), (2, 1));
    assert_eq!(p.stage_1_steps, Some(40));
    assert_eq!(p.dropped_stale_epoch, 10);
    assert_eq!(p.env_steps, 52);
    // Offline = the 40 stage-1 online transitions (the 36 demo transitions are gone); online =
    // the 12 stage-2 ones.
    assert_eq!(DEMOS * DEMO_LEN, 36);
    let offline = manifest.offline.expect("stage 2 has an offline buffer");
    assert_eq!((offline.len, offline.capacity), (40, 1000));
    assert_eq!(manifest.online.len, 12);
    // Optimiser states were kept: Adam's step counts run on over the transition.
    assert_eq!(adam_step_count(&pair.run_dir, "critic"), (G * 9) as i64);
    assert_eq!(adam_step_count(&pair.run_dir, "actor"), (G * 9) as i64);

    // The metrics rows show the stage change with its step.
    let csv = std::fs::read_to_string(pair.run_dir.join("metrics.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let last: Vec<String> = csv
        .lines()
        .last()
        .unwrap()
        .split(',')
        .map(String::from)
        .collect();
    assert_eq!(last[col("stage")], "2");
    assert_eq!(last[col("train_stats/stage_1_steps")], "40");
    assert_eq!(last[col("learner/dropped_stale_epoch")], "10");
    assert_eq!(last[col("learner/replay_offline")], "40");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_stage_1_only_the_end_of_stage_1_ends_the_run() {
    let (_dir, mut pair, mut client) = start("  stage_1_only: true\n").await;
    push(&mut client, batches(0..20, 5, 0)).await.unwrap();
    wait_health(&mut client, Duration::from_secs(30), |h| h.env_steps == 20).await;

    // Successful episodes until the curriculum server ends stage 1, and with it the run.
    let mut cur = pair.curriculum.client().await;
    for _ in 0..5000 {
        if pair.learner.child.try_wait().unwrap().is_some() {
            break;
        }
        let Ok(lease) = cur
            .acquire(rfcl_proto::v1::AcquireRequest {
                actor_id: 9,
                env_index: 0,
                eval: false,
            })
            .await
        else {
            break;
        };
        let lease = lease.into_inner();
        let _ = cur.report(success_report(&lease)).await;
    }
    let status = pair.learner.wait(Duration::from_secs(60));
    assert!(status.success(), "{status}");
    let manifest = checkpoint::read_manifest(&checkpoint::checkpoint_dir(&pair.run_dir))
        .unwrap()
        .unwrap();
    assert_eq!(manifest.progress.env_steps, 20);
    assert_eq!(
        (manifest.progress.stage, manifest.progress.stage_epoch),
        (1, 1)
    );
    assert!(pair.run_dir.join("policy.safetensors").exists());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn load_actor_and_critic_false_start_stage_2_afresh_and_publish_the_fresh_actor() {
    let (_dir, mut pair, mut client) = start("  load_actor: false\n  load_critic: false\n").await;

    push(&mut client, batches(0..40, 8, 0)).await.unwrap();
    let h = wait_health(&mut client, Duration::from_secs(60), |h| {
        h.env_steps == 40 && h.updates == G * 8
    })
    .await;
    let stage_1_version = h.policy_version;
    pair.curriculum.drive_to_stage_2().await;

    // The fresh actor is published at the stage change, before any stage-2 update.
    push(&mut client, batches(40..48, 8, 1)).await.unwrap();
    let h = wait_health(&mut client, Duration::from_secs(30), |h| h.env_steps == 48).await;
    assert_eq!(h.updates, G * 8);
    assert_eq!(h.policy_version, stage_1_version + 1);
    push(&mut client, batches(48..52, 4, 1)).await.unwrap();
    wait_health(&mut client, Duration::from_secs(30), |h| h.updates == G * 9).await;

    // Fresh Adam states: the step counts hold stage 2's one iteration only.
    assert!(pair.learner.sigterm().success());
    for optimiser in ["critic", "actor", "temperature"] {
        assert_eq!(
            adam_step_count(&pair.run_dir, optimiser),
            G as i64,
            "{optimiser}"
        );
    }
}

/// The step count of `optimiser`'s Adam in the run's last checkpoint.
fn adam_step_count(run_dir: &Path, optimiser: &str) -> i64 {
    let ckpt = checkpoint::checkpoint_dir(run_dir);
    let manifest = checkpoint::read_manifest(&ckpt).unwrap().unwrap();
    let optimizers = tch::Tensor::read_safetensors(ckpt.join(&manifest.optimizers_file)).unwrap();
    let name = format!("{optimiser}/step");
    optimizers
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, t)| t.int64_value(&[]))
        .unwrap()
}
