//! `cargo bench -p rfcl-learner --bench checkpoint_io`: what a learner checkpoint costs, in
//! seconds and bytes written, for a PointMaze-size and a paper-size replay (printed as JSON lines).
//!
//! Each case fills the online buffer (and a demo-size offline buffer), writes a first checkpoint
//! (everything is new), then pushes the rows a run adds between two checkpoints and writes the
//! next one: that second checkpoint is the cost a run pays every `sac.save_every_s`.
//!
//! * `pointmaze`: obs 7, action 2, [64, 64] networks, 2 critics; 100,000 rows stored (the end of
//!   a `configs/pointmaze_test.yml` run), then 54,000 new rows (60 s at about 900 env steps/s).
//! * `paper`: obs 42, action 8, [256, 256, 256] networks, 10 critics; the 1,000,000-row buffer
//!   full (wrapped), then 6,000 new rows (60 s at about 100 env steps/s).
//!
//! Bytes written = the sizes of the data files a checkpoint created (every data file has a
//! generation-unique name) plus its manifest. Environment: `RFCL_BENCH_DIR` (where to write,
//! default the system temp dir), `RFCL_BENCH_REPEATS` (second checkpoints timed, best reported,
//! default 3).
use std::collections::HashSet;
use std::path::Path;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rfcl_core::config::{NetworkConfig, SacConfig, UtdMode};
use rfcl_learner::checkpoint::{self, Extras, Progress};
use rfcl_learner::limiter::UtdLimiter;
use rfcl_learner::replay::{Replay, ReplayBuffer};
use rfcl_learner::sac::Sac;

struct Case {
    name: &'static str,
    obs: usize,
    action: usize,
    hidden: Vec<u32>,
    critics: u32,
    capacity: usize,
    stored: usize,
    new_rows: usize,
}

fn push_rows(buffer: &mut ReplayBuffer, rows: usize, rng: &mut ChaCha8Rng) {
    let (d, a) = (buffer.obs_dim(), buffer.action_dim());
    let mut obs = vec![0.0f32; d];
    let mut act = vec![0.0f32; a];
    let mut next = vec![0.0f32; d];
    for _ in 0..rows {
        obs.iter_mut().for_each(|v| *v = rng.random());
        act.iter_mut().for_each(|v| *v = rng.random());
        next.iter_mut().for_each(|v| *v = rng.random());
        buffer
            .push(&obs, &act, rng.random(), 1.0, &next)
            .expect("dims match");
    }
}

fn files(dir: &Path) -> HashSet<String> {
    std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .flatten()
                .map(|e| e.file_name().to_string_lossy().to_string())
                .collect()
        })
        .unwrap_or_default()
}

/// One checkpoint: seconds and bytes written (new data files + the manifest).
fn save(dir: &Path, sac: &Sac, replay: &mut Replay, extras: &Extras<'_>) -> (f64, u64) {
    let before = files(dir);
    let start = Instant::now();
    checkpoint::save(dir, sac, replay, extras).expect("checkpoint");
    let secs = start.elapsed().as_secs_f64();
    let bytes = files(dir)
        .into_iter()
        .filter(|n| !before.contains(n) || n == checkpoint::MANIFEST)
        .map(|n| std::fs::metadata(dir.join(n)).map_or(0, |m| m.len()))
        .sum();
    (secs, bytes)
}

fn main() {
    let root = std::env::var_os("RFCL_BENCH_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(std::env::temp_dir);
    let repeats: usize = std::env::var("RFCL_BENCH_REPEATS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(3);
    tch::set_num_threads(1);
    let cases = [
        Case {
            name: "pointmaze",
            obs: 7,
            action: 2,
            hidden: vec![64, 64],
            critics: 2,
            capacity: 1_000_000,
            stored: 100_000,
            new_rows: 54_000,
        },
        Case {
            name: "paper",
            obs: 42,
            action: 8,
            hidden: vec![256, 256, 256],
            critics: 10,
            capacity: 1_000_000,
            stored: 1_200_000,
            new_rows: 6_000,
        },
    ];
    for case in cases {
        let sac_cfg = SacConfig {
            critic_ensemble: case.critics,
            target_pool: case.critics,
            ..SacConfig::default()
        };
        let net = NetworkConfig {
            actor_features: case.hidden.clone(),
            critic_features: case.hidden.clone(),
            ..NetworkConfig::default()
        };
        let sac = Sac::new(case.obs, case.action, &sac_cfg, &net, 0).expect("agent");
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut online =
            ReplayBuffer::new("online", case.capacity, case.obs, case.action).expect("buffer");
        push_rows(&mut online, case.stored, &mut rng);
        let mut offline =
            ReplayBuffer::new("offline", 1500, case.obs, case.action).expect("buffer");
        push_rows(&mut offline, 1500, &mut rng);
        let mut replay = Replay::new(online, Some(offline), 0);
        let progress = Progress::default();
        let limiter = UtdLimiter::new(UtdMode::Sync, 32, 16, 0);
        let extras = Extras {
            run_name: "bench",
            config_yaml: "name: bench\n",
            progress: &progress,
            limiter: &limiter,
        };
        let dir = tempfile::tempdir_in(&root).expect("temp dir");
        let (first_s, first_bytes) = save(dir.path(), &sac, &mut replay, &extras);
        let mut best = (f64::INFINITY, 0u64);
        for _ in 0..repeats {
            push_rows(&mut replay.online, case.new_rows, &mut rng);
            let (s, b) = save(dir.path(), &sac, &mut replay, &extras);
            if s < best.0 {
                best = (s, b);
            }
        }
        println!(
            "{}",
            serde_json::json!({
                "case": case.name,
                "obs_dim": case.obs,
                "action_dim": case.action,
                "online_rows": replay.online.len(),
                "capacity": case.capacity,
                "new_rows": case.new_rows,
                "first_checkpoint_s": first_s,
                "first_checkpoint_bytes": first_bytes,
                "next_checkpoint_s": best.0,
                "next_checkpoint_bytes": best.1,
            })
        );
    }
}
