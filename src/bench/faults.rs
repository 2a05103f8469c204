//! `rfcl bench faults`: fault injection. Seeded whole `rfcl train` runs on a PointMaze config, each
//! SIGKILLing one kind of process (a train actor, an eval actor, the learner, the curriculum
//! server) at a random moment, some twice, against an undisturbed run; every run should reach its
//! bar with every loss accounted for in its summary (restarts and what each rolled back, respawns,
//! expired leases, refused reports, transitions lost between shared-memory frames).
//!
//! Run 0 is undisturbed; run i > 0 kills [`KINDS`]`[(i - 1) % 4]`, twice when `i % 3 == 0`, at
//! times drawn from `seed + i` between [`KILL_FROM_S`] and [`KILL_UNTIL_S`] after the session's
//! processes are up. The runs' logs and run directories stay in `--out`.
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use serde_json::Value;

/// What a run kills: the child's name prefix in `processes.json`.
pub const KINDS: [&str; 4] = ["actor-", "eval-actor-", "learner", "curriculum-server"];
/// Kill moments, seconds after `processes.json` appears (a PointMaze test run takes 2-4 min).
pub const KILL_FROM_S: f64 = 10.0;
pub const KILL_UNTIL_S: f64 = 90.0;
/// Longest a disturbed run may take.
const RUN_LIMIT: Duration = Duration::from_secs(1800);

#[derive(Debug, Clone, Serialize)]
pub struct FaultRun {
    pub run: u32,
    /// What was killed ("none" for the undisturbed run) and when (s after start-up).
    pub killed: String,
    pub kill_times_s: Vec<f64>,
    pub ending: String,
    pub reached_bar: bool,
    /// Env steps and run wall time to 90 % eval success.
    pub env_steps_to_bar: Option<u64>,
    pub wall_s_to_bar: Option<f64>,
    pub service_restarts: u64,
    pub rolled_back_env_steps: u64,
    pub rolled_back_reports: u64,
    pub actor_respawns: u64,
    pub expired_leases: u64,
    pub refused_reports: u64,
    /// Of which duplicates (a report the curriculum had already applied, e.g. resent after a
    /// restart).
    pub duplicate_reports: u64,
    pub shm_lost_records: u64,
    pub refused_batches: u64,
}

/// `runs` runs (the first undisturbed) of `config` with 5 generated demos, into `out`.
pub fn run(config: &Path, runs: u32, seed: u64, bar: f64, out: &Path) -> Result<Vec<FaultRun>> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let demos = out.join("demos.h5");
    if !demos.exists() {
        crate::generate_demos("pointmaze", 5, &demos, 0)?;
    }
    let mut results = Vec::new();
    for i in 0..runs {
        let mut rng = ChaCha8Rng::seed_from_u64(seed + u64::from(i));
        let (kind, kills) = match i {
            0 => ("none", 0),
            _ => (
                KINDS[(i as usize - 1) % KINDS.len()],
                if i % 3 == 0 { 2 } else { 1 },
            ),
        };
        let mut times: Vec<f64> = (0..kills)
            .map(|_| rng.random_range(KILL_FROM_S..KILL_UNTIL_S))
            .collect();
        times.sort_by(f64::total_cmp);
        let started = Instant::now();
        eprintln!(
            "faults: run {}/{runs}: kill {} x{kills} at {times:.0?} s",
            i + 1,
            kind.trim_end_matches('-')
        );
        let result = one_run(config, &demos, out, i, kind, &times, bar)?;
        eprintln!(
            "faults: run {}/{runs} {} ({}) in {:.0} s",
            i + 1,
            if result.reached_bar {
                "reached its bar"
            } else {
                "did NOT reach its bar"
            },
            result.ending,
            started.elapsed().as_secs_f64()
        );
        results.push(result);
    }
    Ok(results)
}

fn one_run(
    config: &Path,
    demos: &Path,
    out: &Path,
    index: u32,
    kind: &str,
    times: &[f64],
    bar: f64,
) -> Result<FaultRun> {
    let run_dir = out.join(format!("run-{index:02}"));
    let _ = std::fs::remove_dir_all(&run_dir);
    let log_path = out.join(format!("run-{index:02}.log"));
    let log = std::fs::File::create(&log_path)?;
    let exe = std::env::current_exe()?;
    let mut child = Command::new(&exe)
        .arg("train")
        .arg(config)
        .arg(format!("train.dataset_path={}", demos.display()))
        .arg(format!("service.stop_at_eval_success={bar}"))
        .arg("--run-dir")
        .arg(&run_dir)
        .stdin(Stdio::null())
        .stdout(Stdio::from(log.try_clone()?))
        .stderr(Stdio::from(log))
        .spawn()
        .with_context(|| format!("starting {} train", exe.display()))?;
    let deadline = Instant::now() + RUN_LIMIT;
    let processes = run_dir.join("processes.json");
    while !processes.exists() {
        if child.try_wait()?.is_some() || Instant::now() > deadline {
            bail!("run {index} did not start: see {}", log_path.display());
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let up = Instant::now();
    let mut pending = times.iter();
    let mut next = pending.next();
    let status = loop {
        if let Some(status) = child.try_wait()? {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            bail!(
                "run {index} did not end within {RUN_LIMIT:?}: see {}",
                log_path.display()
            );
        }
        if let Some(&at) = next {
            if up.elapsed().as_secs_f64() >= at {
                kill_one(&processes, kind)?;
                next = pending.next();
            }
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    let summary_path = run_dir.join("summary.json");
    let summary: Value =
        serde_json::from_str(&std::fs::read_to_string(&summary_path).with_context(|| {
            format!(
                "run {index} ({status}) wrote no summary: see {}",
                log_path.display()
            )
        })?)
        .with_context(|| format!("parsing {}", summary_path.display()))?;
    let u = |key: &str| summary[key].as_u64().unwrap_or(0);
    let to_bar = summary["to_success"]
        .as_array()
        .and_then(|m| {
            m.iter()
                .find(|m| m["threshold"].as_f64() == Some(0.9))
                .cloned()
        })
        .unwrap_or(Value::Null);
    let restarts = summary["service_restarts"]
        .as_array()
        .cloned()
        .unwrap_or_default();
    let rolled = |key: &str| -> u64 {
        restarts
            .iter()
            .map(|r| r["rolled_back"][key].as_u64().unwrap_or(0))
            .sum()
    };
    let ending = summary["ending"].as_str().unwrap_or("unknown").to_owned();
    Ok(FaultRun {
        run: index,
        killed: kind.trim_end_matches('-').to_owned(),
        kill_times_s: times.to_vec(),
        reached_bar: ending == "eval_success",
        ending,
        env_steps_to_bar: to_bar["env_steps"].as_u64(),
        wall_s_to_bar: to_bar["wall_s"].as_f64(),
        service_restarts: restarts.len() as u64,
        rolled_back_env_steps: rolled("env_steps"),
        rolled_back_reports: rolled("reports"),
        actor_respawns: u("actor_respawns"),
        expired_leases: u("expired_leases"),
        refused_reports: u("refused_reports"),
        duplicate_reports: summary["refused_reports_by_reason"]["duplicate"]
            .as_u64()
            .unwrap_or(0),
        shm_lost_records: u("transitions_lost_shm"),
        refused_batches: u("refused_batches"),
    })
}

/// SIGKILLs the first running child whose name starts with `prefix`.
fn kill_one(processes: &Path, prefix: &str) -> Result<()> {
    let doc: Value = serde_json::from_str(&std::fs::read_to_string(processes)?)
        .with_context(|| format!("parsing {}", processes.display()))?;
    let victim = doc["children"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|c| c["name"].as_str().is_some_and(|n| n.starts_with(prefix)))
        .and_then(|c| Some((c["name"].as_str()?.to_owned(), c["pid"].as_i64()?)))
        .with_context(|| format!("no {prefix}* in {}", processes.display()))?;
    eprintln!("faults:   SIGKILL {} (pid {})", victim.0, victim.1);
    if let Some(pid) = rustix::process::Pid::from_raw(victim.1 as i32) {
        let _ = rustix::process::kill_process(pid, rustix::process::Signal::KILL);
    }
    Ok(())
}

/// The results as a Markdown table (for benches/RESULTS.md).
pub fn table(results: &[FaultRun]) -> String {
    let mut s = String::from(
        "| run | killed | at (s) | ending | env steps to 90 % | wall s to 90 % | service restarts | rolled back env steps / reports | actor respawns | expired leases | refused reports (duplicates) | shm records lost | refused batches |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in results {
        let times: Vec<String> = r.kill_times_s.iter().map(|t| format!("{t:.0}")).collect();
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} / {} | {} | {} | {} ({}) | {} | {} |\n",
            r.run,
            r.killed,
            if times.is_empty() {
                "-".into()
            } else {
                times.join(", ")
            },
            r.ending,
            r.env_steps_to_bar.map_or("-".into(), |v| v.to_string()),
            r.wall_s_to_bar.map_or("-".into(), |v| format!("{v:.0}")),
            r.service_restarts,
            r.rolled_back_env_steps,
            r.rolled_back_reports,
            r.actor_respawns,
            r.expired_leases,
            r.refused_reports,
            r.duplicate_reports,
            r.shm_lost_records,
            r.refused_batches,
        ));
    }
    s
}

/// Where the runs go when `--out` is not given.
pub fn default_out() -> PathBuf {
    PathBuf::from("runs/bench-faults")
}
