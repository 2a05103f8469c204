//! `rfcl bench e2e`: end-to-end env steps per second of whole `rfcl train` runs on PointMaze with
//! 1, 2, 4, ... actors.
//!
//! Each run is this binary's own `rfcl train` on the given config with 5 generated demos, in
//! `async` UTD mode (learner and actors flat out: the sync mode would report the learner's update
//! rate instead of what the actors and transports deliver), stopped with SIGTERM after the given
//! time. The rate is taken from the learner's metrics.csv (env steps received over its own wall
//! clock, between its first and last rows), so process start-up is not counted. Every process of
//! the run shares this machine's cores, as in a real run.
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use serde::Serialize;

#[derive(Debug, Clone, Serialize)]
pub struct E2eResult {
    pub actors: u32,
    pub env_steps: u64,
    pub seconds: f64,
    pub env_steps_per_s: f64,
    /// Critic updates per env step the learner achieved meanwhile (async mode).
    pub achieved_utd: f64,
}

/// One run per entry of `actors`, each `seconds` long.
pub fn run(config: &Path, actors: &[u32], seconds: f64) -> Result<Vec<E2eResult>> {
    let dir = tempfile::tempdir()?;
    let demos = dir.path().join("demos.h5");
    crate::demos::generate("pointmaze", 5, &demos, 0)?;
    let exe = std::env::current_exe()?;
    let mut results = Vec::new();
    for &k in actors {
        let run_dir = dir.path().join(format!("run-{k}"));
        let log = std::fs::File::create(dir.path().join(format!("train-{k}.log")))?;
        eprintln!("e2e: {k} actor(s) for {seconds:.0} s ...");
        let mut child = Command::new(&exe)
            .arg("train")
            .arg(config)
            .arg(format!("train.dataset_path={}", demos.display()))
            .args([
                "train.steps=1000000000",
                &format!("service.num_actors={k}"),
                "sac.utd_mode=async",
            ])
            .arg("--run-dir")
            .arg(&run_dir)
            .stdout(Stdio::from(log.try_clone()?))
            .stderr(Stdio::from(log))
            .spawn()
            .with_context(|| format!("starting {} train", exe.display()))?;
        std::thread::sleep(Duration::from_secs_f64(seconds));
        let pid = rustix::process::Pid::from_child(&child);
        let _ = rustix::process::kill_process(pid, rustix::process::Signal::TERM);
        let deadline = Instant::now() + Duration::from_secs(60);
        while child.try_wait()?.is_none() {
            if Instant::now() > deadline {
                let _ = child.kill();
                bail!("rfcl train with {k} actors did not stop within 60 s of SIGTERM");
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        results.push(rate_from_metrics(&run_dir.join("metrics.csv"), k)?);
    }
    Ok(results)
}

/// Env steps/s between the first and last rows of a learner's metrics.csv.
fn rate_from_metrics(path: &Path, actors: u32) -> Result<E2eResult> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading {} (did the run start?)", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let column = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .with_context(|| format!("{}: no column '{name}'", path.display()))
    };
    let (steps_col, time_col, updates_col) = (
        column("env_steps")?,
        column("time/total")?,
        column("train/training_steps")?,
    );
    let rows: Vec<Vec<f64>> = lines
        .map(|l| {
            l.split(',')
                .map(|v| v.parse().unwrap_or(f64::NAN))
                .collect()
        })
        .filter(|r: &Vec<f64>| r.len() == header.len())
        .collect();
    let (Some(first), Some(last)) = (rows.first(), rows.last()) else {
        bail!("{}: no metrics rows: the run was too short", path.display());
    };
    let steps = last[steps_col] - first[steps_col];
    let seconds = last[time_col] - first[time_col];
    if rows.len() < 2 || seconds <= 0.0 {
        bail!(
            "{}: fewer than two metrics rows: run longer (--seconds)",
            path.display()
        );
    }
    Ok(E2eResult {
        actors,
        env_steps: steps as u64,
        seconds,
        env_steps_per_s: steps / seconds,
        achieved_utd: (last[updates_col] - first[updates_col]) / steps.max(1.0),
    })
}
