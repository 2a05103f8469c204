//! A diverging run (absurd learning rates: the losses are NaN or infinite within two iterations)
//! stops at its first non-finite loss or weight, names it with the update and env step, exits
//! non-zero, and never publishes, exports or checkpoints non-finite weights.
mod service_support;

use std::time::Duration;

use rfcl_learner::checkpoint;
use rfcl_policy::PolicyNet;
use rfcl_proto::v1;
use service_support::*;

const W: u64 = 8;

fn finite(t: &tch::Tensor) -> bool {
    t.isfinite().all().int64_value(&[]) != 0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_diverging_run_stops_with_a_clear_error_and_writes_no_non_finite_weights() {
    let dir = tempfile::tempdir().unwrap();
    let demos = write_demos(dir.path());
    // The test config checkpoints every 40 env steps: 200 would write several if nothing stopped
    // the run.
    let config = write_config(
        dir.path(),
        W,
        100_000,
        "  critic_lr: 1.0e+30\n  actor_lr: 1.0e+30\n  temp_lr: 1.0e+30\n",
    );
    let run_dir = dir.path().join("run");
    let curriculum = Curriculum::start(&config, &demos, &run_dir);
    let args = Learner::args(&config, &curriculum.grpc, &demos, &run_dir);
    let args: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    let mut learner = Learner::start(&args);
    let mut client = learner.client().await;
    let cfg = rfcl_core::config::resolve_file(&config, &[]).unwrap();

    // Every version an actor can receive.
    let mut watch = client
        .watch_policy(v1::WatchPolicyRequest { after_version: 0 })
        .await
        .unwrap()
        .into_inner();
    let watcher = tokio::spawn(async move {
        let mut versions = Vec::new();
        while let Ok(Some(weights)) = watch.message().await {
            versions.push(weights);
        }
        versions
    });

    // The stream may be cut when the learner stops: its answer does not matter.
    let _ = push(&mut client, batches(0..200, 4, 0)).await;
    let status = learner.wait(Duration::from_secs(60));
    assert!(!status.success(), "a diverged run must exit non-zero");
    let stderr = learner.stderr_text();
    let line = stderr
        .lines()
        .find(|l| l.starts_with("error:"))
        .unwrap_or_else(|| panic!("no error line; stderr:\n{stderr}"));
    assert!(line.contains("training diverged"), "{line}");
    assert!(
        line.contains("loss") || line.contains("holds NaN or infinite values"),
        "{line}"
    );
    assert!(line.contains("env step"), "{line}");
    assert!(line.contains("critic update"), "{line}");

    // Nothing non-finite left the learner.
    let versions = tokio::time::timeout(Duration::from_secs(10), watcher)
        .await
        .expect("the policy stream ends with the learner")
        .unwrap();
    assert!(!versions.is_empty());
    for weights in &versions {
        let tensors = safetensors::SafeTensors::deserialize(&weights.safetensors).unwrap();
        for (name, view) in tensors.tensors() {
            let values: Vec<f32> = view
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
                .collect();
            assert!(
                values.iter().all(|v| v.is_finite()),
                "policy version {} publishes non-finite {name}",
                weights.version
            );
        }
        PolicyNet::from_safetensors(&weights.safetensors, &cfg, OBS, ACT).unwrap();
    }
    assert!(
        !run_dir.join("policy.safetensors").exists(),
        "a diverged run exports no policy"
    );
    let ckpt = checkpoint::checkpoint_dir(&run_dir);
    if let Some(manifest) = checkpoint::read_manifest(&ckpt).unwrap() {
        for file in [&manifest.networks_file, &manifest.optimizers_file] {
            for (name, t) in tch::Tensor::read_safetensors(ckpt.join(file)).unwrap() {
                assert!(finite(&t), "checkpoint {file} holds non-finite {name}");
            }
        }
    }
}
