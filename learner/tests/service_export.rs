//! The end of a run: the learner stops by itself once `train.steps` env steps arrived, exits 0
//! after its final checkpoint, and exports the policy; the PyTorch snippet of docs/POLICY.md
//! loads that export and acts exactly like the Rust policy.
mod service_support;

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use rfcl_learner::checkpoint;
use rfcl_policy::PolicyNet;
use rfcl_testkit::child;
use service_support::*;

const W: u64 = 8;
const STEPS: u64 = 60;

/// The ```python block of docs/POLICY.md.
fn policy_snippet() -> String {
    let doc =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/POLICY.md"))
            .unwrap();
    let start = doc.find("```python\n").expect("a python block") + "```python\n".len();
    let end = start + doc[start..].find("```").unwrap();
    doc[start..end].to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_budget_ends_the_run_with_a_checkpoint_and_an_export_pytorch_can_load() {
    let dir = tempfile::tempdir().unwrap();
    // data_action_scale: the export records the env-action scale of spec 6.4, and GetRunInfo
    // gives actors the same.
    let config = write_config(dir.path(), W, STEPS, "");
    add_train_keys(&config, "  data_action_scale: 1.5\n");
    let mut pair = Pair::start(dir.path(), config, &[]);
    let mut client = pair.learner.client().await;
    // Actors learn s from the run description and step their envs with a / s (spec 6.4).
    let info = client
        .get_run_info(rfcl_proto::v1::GetRunInfoRequest::default())
        .await
        .unwrap()
        .into_inner();
    let sent = rfcl_proto::convert::action_scale(&info)
        .unwrap()
        .expect("RunInfo.action_scale with data_action_scale set");

    let summary = push(&mut client, batches(0..STEPS, 10, 0)).await.unwrap();
    assert_eq!(summary.accepted, STEPS);
    let status = pair.learner.wait(Duration::from_secs(60));
    assert!(
        status.success(),
        "the learner exits 0 at the budget: {status}"
    );

    let manifest = checkpoint::read_manifest(&checkpoint::checkpoint_dir(&pair.run_dir))
        .unwrap()
        .unwrap();
    assert_eq!(manifest.progress.env_steps, STEPS);
    let iterations = earned(STEPS, W);
    assert_eq!(manifest.progress.critic_updates, G * iterations);

    let (policy, desc) = PolicyNet::from_export(&pair.run_dir).unwrap();
    assert_eq!((desc.shape.obs_dim, desc.shape.action_dim), (OBS, ACT));
    assert_eq!(desc.shape.actor_features, vec![16, 16]);
    assert_eq!(
        (desc.policy_version, desc.env_steps),
        (1 + iterations, STEPS)
    );
    assert_eq!(desc.env_id, "PointMaze-v0");
    let scale = desc
        .action_scale
        .clone()
        .expect("data_action_scale was set");
    assert_eq!(scale.len(), ACT);
    assert!(scale.iter().all(|&s| s.is_finite() && s > 0.0));
    assert!(scale.iter().any(|&s| s != 1.0), "{scale:?}");
    assert_eq!(sent, scale, "the actors' scale is the exported one");

    // The documented PyTorch snippet acts like the Rust policy.
    let python = Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing (scripts/setup.sh creates the venv)",
        python.display()
    );
    let script = dir.path().join("rfcl_policy.py");
    std::fs::write(&script, policy_snippet()).unwrap();
    let obs = [0.3f32, -0.7, 0.05, 0.9];
    let from_torch: Vec<f32> = serde_json::from_str(&child::succeed(
        Command::new(&python)
            .arg(&script)
            .arg(&pair.run_dir)
            .args(obs.iter().map(|o| o.to_string())),
    ))
    .unwrap();
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
    let agent = policy.act(&obs, true, &mut rng);
    // rfcl_actor::rollout::env_action: clip(a / s, -1, 1).
    let from_rust: Vec<f32> = agent
        .iter()
        .zip(&scale)
        .map(|(a, s)| (a / s).clamp(-1.0, 1.0))
        .collect();
    assert_eq!(from_torch.len(), ACT);
    for (t, r) in from_torch.iter().zip(&from_rust) {
        assert!(
            (t - r).abs() < 1e-5,
            "torch {from_torch:?} vs rust {from_rust:?}"
        );
    }

    // So does rfcl_sim.load_policy, with NumPy alone, on the run directory and on the file.
    let numpy = |path: &Path| -> Vec<f32> {
        let code = "import json, sys; from rfcl_sim import load_policy; \
                    p = load_policy(sys.argv[1]); \
                    print(json.dumps(p([float(x) for x in sys.argv[2:]]).tolist()))";
        let out = child::succeed(
            Command::new(&python)
                .env(
                    "PYTHONPATH",
                    Path::new(env!("CARGO_MANIFEST_DIR")).join("../python"),
                )
                .args(["-c", code])
                .arg(path)
                .args(obs.iter().map(|o| o.to_string())),
        );
        serde_json::from_str(&out).unwrap()
    };
    for path in [
        pair.run_dir.clone(),
        pair.run_dir.join("policy.safetensors"),
    ] {
        let from_numpy = numpy(&path);
        assert_eq!(from_numpy.len(), ACT);
        for (n, r) in from_numpy.iter().zip(&from_rust) {
            assert!(
                (n - r).abs() < 1e-5,
                "numpy {from_numpy:?} vs rust {from_rust:?}"
            );
        }
    }
}

/// A budget between two iterations ends with one more iteration on the steps since the last, so
/// the final policy has learned from every env step and carries the budget as its env steps (the
/// eval point an evaluation at the budget stands for).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_budget_between_iterations_ends_with_one_more_iteration() {
    const BETWEEN: u64 = 62;
    assert_ne!(BETWEEN % K, 0);
    let dir = tempfile::tempdir().unwrap();
    let mut pair = start_pair(dir.path(), W, BETWEEN, "", &[]);
    let mut client = pair.learner.client().await;
    push(&mut client, batches(0..BETWEEN, 10, 0)).await.unwrap();
    let status = pair.learner.wait(Duration::from_secs(60));
    assert!(status.success(), "{status}");

    let iterations = earned(BETWEEN, W) + 1;
    let manifest = checkpoint::read_manifest(&checkpoint::checkpoint_dir(&pair.run_dir))
        .unwrap()
        .unwrap();
    assert_eq!(
        (
            manifest.progress.env_steps,
            manifest.progress.critic_updates
        ),
        (BETWEEN, G * iterations)
    );
    let (_, desc) = PolicyNet::from_export(&pair.run_dir).unwrap();
    assert_eq!(
        (desc.policy_version, desc.env_steps),
        (1 + iterations, BETWEEN)
    );
}
