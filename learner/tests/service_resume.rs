//! SIGKILL after a checkpoint, then `--resume` (or a plain restart on the same run directory):
//! the resumed learner holds exactly the checkpointed weights, optimiser states, temperature,
//! counters, RNG states and both buffers, and, fed the same transitions, ends bit for bit where an uninterrupted run ends. A learner
//! killed before its first env-step checkpoint resumes from its wall-time one
//! (`sac.save_every_s`).
mod service_support;

use std::path::Path;
use std::time::Duration;

use rfcl_learner::checkpoint::{self, Manifest};
use rfcl_proto::auth::AuthChannel;
use rfcl_proto::v1::learner_client::LearnerClient;
use service_support::*;

const W: u64 = 8;

/// Everything a checkpoint holds, in comparable form.
#[derive(Debug, PartialEq)]
struct Snapshot {
    networks: Vec<(String, Vec<f64>)>,
    optimizers: Vec<(String, Vec<f64>)>,
    replay: Vec<u8>,
    manifest: serde_json::Value,
}

fn values(t: &tch::Tensor) -> Vec<f64> {
    Vec::<f64>::try_from(t.to_kind(tch::Kind::Double).flatten(0, -1)).unwrap()
}

fn snapshot(run_dir: &Path) -> (Snapshot, Manifest) {
    let dir = checkpoint::checkpoint_dir(run_dir);
    let manifest = checkpoint::read_manifest(&dir)
        .unwrap()
        .expect("a checkpoint");
    let read = |file: &str| {
        let mut tensors: Vec<(String, Vec<f64>)> = tch::Tensor::read_safetensors(dir.join(file))
            .unwrap()
            .iter()
            .map(|(n, t)| (n.clone(), values(t)))
            .collect();
        tensors.sort_by(|a, b| a.0.cmp(&b.0));
        tensors
    };
    // Everything but the file names, the generation, the wall-clock time and the manifest's
    // checksum (which covers those).
    let mut json = serde_json::to_value(&manifest).unwrap();
    for key in ["generation", "networks_file", "optimizers_file", "checksum"] {
        json.as_object_mut().unwrap().remove(key);
    }
    json["progress"].as_object_mut().unwrap().remove("wall_ms");
    for buffer in ["online", "offline"] {
        if let Some(segments) = json[buffer]["segments"].as_array_mut() {
            for segment in segments {
                segment.as_object_mut().unwrap().remove("file");
            }
        }
    }
    // The replay: every segment file's bytes, in order.
    let mut replay = Vec::new();
    for meta in std::iter::once(&manifest.online).chain(manifest.offline.as_ref()) {
        for segment in &meta.segments {
            replay.extend(std::fs::read(dir.join(&segment.file)).unwrap());
        }
    }
    let snap = Snapshot {
        networks: read(&manifest.networks_file),
        optimizers: read(&manifest.optimizers_file),
        replay,
        manifest: json,
    };
    (snap, manifest)
}

/// The env-step column and the spec 5.8 update columns of metrics.csv.
fn curves(run_dir: &Path) -> Vec<Vec<String>> {
    let csv = std::fs::read_to_string(run_dir.join("metrics.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let cols: Vec<usize> = header
        .iter()
        .enumerate()
        .filter(|(_, h)| **h == "env_steps" || h.starts_with("train/") || **h == "policy_version")
        .map(|(i, _)| i)
        .collect();
    csv.lines()
        .skip(1)
        .map(|line| {
            let cells: Vec<&str> = line.split(',').collect();
            cols.iter().map(|&i| cells[i].to_string()).collect()
        })
        .collect()
}

struct Run {
    _curriculum: Curriculum,
    config: std::path::PathBuf,
    demos: std::path::PathBuf,
    run_dir: std::path::PathBuf,
    curriculum_addr: String,
}

impl Run {
    fn new(dir: &Path) -> Run {
        // No wall-time checkpoint in these runs: only the env-step ones, at exact counts.
        Self::with_sac(dir, "  save_every_s: 3600\n", 40)
    }

    /// The test config with `sac_extra` added under `sac` and `save_freq` (40 there) set.
    fn with_sac(dir: &Path, sac_extra: &str, save_freq: u64) -> Run {
        let demos = write_demos(dir);
        let config = write_config(dir, W, 100_000, sac_extra);
        let text = std::fs::read_to_string(&config).unwrap();
        assert!(text.contains("  save_freq: 40\n"));
        let text = text.replace("  save_freq: 40\n", &format!("  save_freq: {save_freq}\n"));
        std::fs::write(&config, text).unwrap();
        let run_dir = dir.join("run");
        let curriculum = Curriculum::start(&config, &demos, &run_dir);
        Run {
            curriculum_addr: curriculum.grpc.clone(),
            _curriculum: curriculum,
            config,
            demos,
            run_dir,
        }
    }

    fn start(&self, resume: bool) -> Learner {
        let mut args = Learner::args(
            &self.config,
            &self.curriculum_addr,
            &self.demos,
            &self.run_dir,
        );
        if resume {
            // --resume RUN_DIR instead of --run-dir RUN_DIR.
            let at = args.iter().position(|a| a == "--run-dir").unwrap();
            args[at] = "--resume".into();
        }
        let args: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
        // Two threads: the critic's two members update in parallel (learner.parallelism
        // members), and that too must resume exactly.
        Learner::start_with_threads(2, &args)
    }
}

/// The manifest of the checkpoint in `ckpt` once one holds `env_steps` (within 30 s).
async fn checkpoint_at(ckpt: &Path, env_steps: u64) -> Manifest {
    let start = std::time::Instant::now();
    loop {
        if let Some(m) = checkpoint::read_manifest(ckpt).unwrap() {
            if m.progress.env_steps == env_steps {
                return m;
            }
        }
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "no checkpoint at {env_steps} env steps within 30 s"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The resumed learner's Health reports the checkpoint's env steps, updates and policy version.
async fn assert_restored(client: &mut LearnerClient<AuthChannel>, manifest: &Manifest) {
    let h = health(client).await;
    let p = &manifest.progress;
    assert_eq!(
        (h.env_steps, h.updates, h.policy_version),
        (p.env_steps, p.critic_updates, p.policy_version)
    );
}

async fn feed(learner: &Learner, range: std::ops::Range<u64>) {
    let mut client = learner.client().await;
    let end = range.end;
    let summary = push(&mut client, batches(range.clone(), 6, 0))
        .await
        .unwrap();
    assert_eq!(summary.accepted, range.end - range.start);
    wait_health(&mut client, Duration::from_secs(60), |h| {
        h.env_steps == end && h.updates == G * earned(end, W)
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_then_resume_restores_everything_and_continues_exactly() {
    // The reference: 80 env steps without interruption.
    let dir_a = tempfile::tempdir().unwrap();
    let a = Run::new(dir_a.path());
    let mut learner = a.start(false);
    feed(&learner, 0..80).await;
    assert!(learner.sigterm().success());
    let (reference, reference_manifest) = snapshot(&a.run_dir);
    assert_eq!(reference_manifest.progress.env_steps, 80);

    // Interrupted: 52 env steps (checkpoint at 40, save_freq), then SIGKILL.
    let dir_b = tempfile::tempdir().unwrap();
    let b = Run::new(dir_b.path());
    let mut learner = b.start(false);
    feed(&learner, 0..52).await;
    let (at_40, manifest_40) = snapshot(&b.run_dir);
    assert_eq!(manifest_40.progress.env_steps, 40);
    assert_eq!(manifest_40.online.len, 40);
    assert_eq!(manifest_40.offline.as_ref().unwrap().len, DEMOS * DEMO_LEN);
    learner.sigkill();

    // Resumed: the state is the checkpoint's, published version and counters included...
    let mut learner = b.start(true);
    let mut client = learner.client().await;
    assert_restored(&mut client, &manifest_40).await;
    let mut watch = client
        .watch_policy(rfcl_proto::v1::WatchPolicyRequest { after_version: 0 })
        .await
        .unwrap()
        .into_inner();
    let weights = watch.message().await.unwrap().unwrap();
    assert_eq!(
        (weights.version, weights.learner_env_steps),
        (manifest_40.progress.policy_version, 40)
    );
    // ...and a checkpoint written right away holds exactly what the killed learner wrote.
    assert!(learner.sigterm().success());
    let (resumed, _) = snapshot(&b.run_dir);
    assert_eq!(resumed.networks, at_40.networks, "weights");
    assert_eq!(resumed.optimizers, at_40.optimizers, "optimiser states");
    assert!(resumed.replay == at_40.replay, "buffer contents");
    assert_eq!(
        resumed.manifest, at_40.manifest,
        "counters, limiter, RNG states"
    );

    // Fed the rest of the same stream, the resumed learner ends where the reference ended.
    let mut learner = b.start(true);
    feed(&learner, 40..80).await;
    assert!(learner.sigterm().success());
    let (finished, _) = snapshot(&b.run_dir);
    assert_eq!(finished.networks, reference.networks, "weights");
    assert_eq!(
        finished.optimizers, reference.optimizers,
        "optimiser states"
    );
    assert!(finished.replay == reference.replay, "buffer contents");
    assert_eq!(finished.manifest, reference.manifest);
    // The curves match too: no row lost, none doubled by the kill.
    let curve = curves(&b.run_dir);
    assert_eq!(curve, curves(&a.run_dir));
    let steps: Vec<&str> = curve.iter().map(|r| r[0].as_str()).collect();
    assert_eq!(steps, ["20", "40", "60", "80"]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_learner_that_finds_its_checkpoint_in_its_run_dir_continues_it() {
    let dir = tempfile::tempdir().unwrap();
    let run = Run::new(dir.path());
    let mut learner = run.start(false);
    feed(&learner, 0..52).await;
    learner.sigkill();
    let (at_40, manifest_40) = snapshot(&run.run_dir);
    assert_eq!(manifest_40.progress.env_steps, 40);

    // Started exactly as the first time (no --resume), as a container engine restarts it.
    let mut learner = run.start(false);
    let mut client = learner.client().await;
    assert_restored(&mut client, &manifest_40).await;
    assert!(learner.sigterm().success());
    let (resumed, _) = snapshot(&run.run_dir);
    assert_eq!(resumed.networks, at_40.networks, "weights");
    assert!(resumed.replay == at_40.replay, "buffer contents");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_learner_killed_before_its_first_step_checkpoint_resumes_from_its_wall_time_one() {
    let dir = tempfile::tempdir().unwrap();
    // An env-step checkpoint the run never reaches.
    let run = Run::with_sac(dir.path(), "  save_every_s: 0.2\n", 1_000_000);
    let mut learner = run.start(false);
    feed(&learner, 0..30).await;
    // Nothing arrives any more: the next wall-time checkpoint holds all 30 env steps.
    let ckpt = checkpoint::checkpoint_dir(&run.run_dir);
    let manifest = checkpoint_at(&ckpt, 30).await;
    assert_eq!(manifest.online.len, 30);
    // With nothing new, no further checkpoint is taken.
    tokio::time::sleep(Duration::from_millis(600)).await;
    let again = checkpoint::read_manifest(&ckpt).unwrap().unwrap();
    assert_eq!(again.generation, manifest.generation);
    learner.sigkill();

    let mut learner = run.start(false);
    let mut client = learner.client().await;
    assert_restored(&mut client, &manifest).await;
    // More rows reach the resumed learner's online buffer: its next wall-time checkpoint writes
    // only the segment they changed (one: 16,384-row segments), keeping the others' files.
    feed_from(&learner, 30..36, 36).await;
    let next = checkpoint_at(&ckpt, 36).await;
    assert_eq!(next.online.segments.len(), 1);
    assert_ne!(next.online.segments[0], manifest.online.segments[0]);
    // The offline buffer (the demos) did not change: its file is the first checkpoint's.
    assert_eq!(next.offline, manifest.offline);
    assert!(learner.sigterm().success());
}

async fn feed_from(learner: &Learner, range: std::ops::Range<u64>, end: u64) {
    let mut client = learner.client().await;
    let summary = push(&mut client, batches(range.clone(), 6, 0))
        .await
        .unwrap();
    assert_eq!(summary.accepted, range.end - range.start);
    wait_health(&mut client, Duration::from_secs(60), |h| h.env_steps == end).await;
}
