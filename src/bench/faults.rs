//! `rfcl bench faults`: fault injection. Seeded whole `rfcl train` runs on a PointMaze config, each
//! disturbing one kind of process (a train actor, an eval actor, the learner, the curriculum
//! server) at a random moment, some twice, against an undisturbed run; every run should reach its
//! bar with every loss accounted for in its summary (restarts and what each rolled back, respawns,
//! expired leases, refused reports, transitions lost between shared-memory frames).
//!
//! A [`Fault`] is a SIGKILL, a hang (SIGSTOP, SIGCONT [`HANG_S`] later, longer than the launcher's
//! `service.hang_timeout_s`) or a damaged checkpoint (one bit flipped in the learner's newest
//! networks file or the curriculum snapshot, then a SIGKILL, so that the restarted process reads
//! it). Run 0 is undisturbed; run i > 0 applies the (fault, kind) pair `(i - 1) % pairs` of the
//! faults asked for, each with the kinds it applies to, twice when `i % 3 == 0`, at times drawn
//! from `seed + i` between [`FAULT_FROM_S`] and [`FAULT_UNTIL_S`] after the session's processes
//! are up. The runs' logs and run directories stay in `--out`, and each run's result is appended to
//! `--out`/results.jsonl as it ends.
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rustix::process::Signal;
use serde::Serialize;
use serde_json::Value;

/// What a run disturbs: the child's name prefix in `processes.json`.
pub const KINDS: [&str; 4] = ["actor-", "eval-actor-", "learner", "curriculum-server"];
/// The processes that own a checkpoint.
const OWNERS: [&str; 2] = ["learner", "curriculum-server"];
/// Fault moments, seconds after `processes.json` appears (a PointMaze test run takes 2-4 min).
pub const FAULT_FROM_S: f64 = 10.0;
pub const FAULT_UNTIL_S: f64 = 90.0;
/// How long a hung process stays stopped: past the default `service.hang_timeout_s` (60 s), so a
/// hung service is restarted by the launcher, and past the actors' 30 s call deadline.
pub const HANG_S: f64 = 75.0;

/// What a disturbed run does to its process.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Fault {
    /// SIGKILL.
    Kill,
    /// SIGSTOP, then SIGCONT [`HANG_S`] later (if it still lives).
    Hang,
    /// One bit of its newest checkpoint flipped, then SIGKILL (learner, curriculum server).
    Corrupt,
}

impl Fault {
    fn kinds(self) -> &'static [&'static str] {
        match self {
            Fault::Kill | Fault::Hang => &KINDS,
            Fault::Corrupt => &OWNERS,
        }
    }
}

/// Every (fault, kind) pair of `faults`, in the order the disturbed runs take them.
fn plan(faults: &[Fault]) -> Vec<(Fault, &'static str)> {
    faults
        .iter()
        .flat_map(|&f| f.kinds().iter().map(move |&k| (f, k)))
        .collect()
}
/// Longest a disturbed run may take.
const RUN_LIMIT: Duration = Duration::from_secs(1800);

#[derive(Debug, Clone, Serialize)]
pub struct FaultRun {
    pub run: u32,
    /// What was done ("none" for the undisturbed run), to which process, and when (s after
    /// start-up).
    pub fault: String,
    pub target: String,
    pub fault_times_s: Vec<f64>,
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
pub fn run(
    config: &Path,
    runs: u32,
    faults: &[Fault],
    seed: u64,
    bar: f64,
    out: &Path,
) -> Result<Vec<FaultRun>> {
    let plan = plan(faults);
    if plan.is_empty() {
        bail!("--faults: name at least one of kill, hang, corrupt");
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let demos = out.join("demos.h5");
    if !demos.exists() {
        crate::demos::generate("pointmaze", 5, &demos, 0)?;
    }
    let jsonl = out.join("results.jsonl");
    std::fs::write(&jsonl, "").with_context(|| format!("writing {}", jsonl.display()))?;
    let mut results = Vec::new();
    for i in 0..runs {
        let mut rng = ChaCha8Rng::seed_from_u64(seed + u64::from(i));
        let (fault, count) = match i {
            0 => (None, 0),
            _ => (
                Some(plan[(i as usize - 1) % plan.len()]),
                if i % 3 == 0 { 2 } else { 1 },
            ),
        };
        let mut times: Vec<f64> = (0..count)
            .map(|_| rng.random_range(FAULT_FROM_S..FAULT_UNTIL_S))
            .collect();
        times.sort_by(f64::total_cmp);
        let started = Instant::now();
        if let Some((fault, kind)) = fault {
            eprintln!(
                "faults: run {}/{runs}: {fault:?} {} x{count} at {times:.0?} s",
                i + 1,
                kind.trim_end_matches('-')
            );
        }
        let disturbance = fault.map(|(fault, kind)| Disturbance { fault, kind, times });
        let result = one_run(config, &demos, out, i, disturbance, &mut rng, bar)?;
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
        // Kept as each run ends, so that a bench stopped later loses none of them.
        let mut line = serde_json::to_string(&result)?;
        line.push('\n');
        std::fs::OpenOptions::new()
            .append(true)
            .open(&jsonl)
            .and_then(|mut f| std::io::Write::write_all(&mut f, line.as_bytes()))
            .with_context(|| format!("writing {}", jsonl.display()))?;
        results.push(result);
    }
    Ok(results)
}

/// The `rfcl train` session of one run: should the bench leave it early (an error), it is stopped
/// like a user would (SIGTERM, then SIGKILL after 30 s), so that no run outlives the bench.
struct Session(std::process::Child);

impl Drop for Session {
    fn drop(&mut self) {
        if !matches!(self.0.try_wait(), Ok(None)) {
            return;
        }
        signal("the session", self.0.id() as i32, Signal::TERM);
        let until = Instant::now() + Duration::from_secs(30);
        while Instant::now() < until {
            if !matches!(self.0.try_wait(), Ok(None)) {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// What one run does, to which kind of process, at which moments (s after start-up).
struct Disturbance {
    fault: Fault,
    kind: &'static str,
    times: Vec<f64>,
}

fn one_run(
    config: &Path,
    demos: &Path,
    out: &Path,
    index: u32,
    disturbance: Option<Disturbance>,
    rng: &mut ChaCha8Rng,
    bar: f64,
) -> Result<FaultRun> {
    let run_dir = out.join(format!("run-{index:02}"));
    let _ = std::fs::remove_dir_all(&run_dir);
    let log_path = out.join(format!("run-{index:02}.log"));
    let log = std::fs::File::create(&log_path)?;
    let exe = std::env::current_exe()?;
    let mut child = Session(
        Command::new(&exe)
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
            .with_context(|| format!("starting {} train", exe.display()))?,
    );
    let deadline = Instant::now() + RUN_LIMIT;
    let processes = run_dir.join("processes.json");
    while !processes.exists() {
        if child.0.try_wait()?.is_some() || Instant::now() > deadline {
            bail!("run {index} did not start: see {}", log_path.display());
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let up = Instant::now();
    let times = disturbance.as_ref().map_or(&[][..], |d| &d.times[..]);
    let mut pending = times.iter();
    let mut next = pending.next();
    let mut stopped: Vec<(i32, Instant)> = Vec::new();
    // When each fault was applied (a damaged checkpoint waits for the first one to exist).
    let mut applied_at = Vec::new();
    let status = loop {
        if let Some(status) = child.0.try_wait()? {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.0.kill();
            bail!(
                "run {index} did not end within {RUN_LIMIT:?}: see {}",
                log_path.display()
            );
        }
        if let (Some(&at), Some(d)) = (next, &disturbance) {
            let now = up.elapsed().as_secs_f64();
            if now >= at {
                let (name, pid) = find(&processes, d.kind)?;
                let applied = match d.fault {
                    Fault::Kill => {
                        signal(&name, pid, Signal::KILL);
                        true
                    }
                    Fault::Hang => {
                        signal(&name, pid, Signal::STOP);
                        stopped.push((pid, Instant::now()));
                        true
                    }
                    Fault::Corrupt => match damage(&run_dir, d.kind, rng)? {
                        Some(file) => {
                            eprintln!("faults:   flipped a bit of {}", file.display());
                            signal(&name, pid, Signal::KILL);
                            true
                        }
                        None => false,
                    },
                };
                if applied {
                    applied_at.push(now);
                    next = pending.next();
                }
            }
        }
        stopped.retain(|&(pid, since)| {
            let over = since.elapsed().as_secs_f64() >= HANG_S;
            if over {
                // A service the launcher restarted meanwhile is gone: ESRCH, nothing to do.
                signal("the hung process", pid, Signal::CONT);
            }
            !over
        });
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
        fault: disturbance
            .as_ref()
            .map_or("none".into(), |d| format!("{:?}", d.fault).to_lowercase()),
        target: disturbance
            .as_ref()
            .map_or("-".into(), |d| d.kind.trim_end_matches('-').to_owned()),
        fault_times_s: applied_at,
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

/// The name and pid of the first running child whose name starts with `prefix`.
fn find(processes: &Path, prefix: &str) -> Result<(String, i32)> {
    let doc: Value = serde_json::from_str(&std::fs::read_to_string(processes)?)
        .with_context(|| format!("parsing {}", processes.display()))?;
    doc["children"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|c| c["name"].as_str().is_some_and(|n| n.starts_with(prefix)))
        .and_then(|c| Some((c["name"].as_str()?.to_owned(), c["pid"].as_i64()? as i32)))
        .with_context(|| format!("no {prefix}* in {}", processes.display()))
}

fn signal(name: &str, pid: i32, signal: Signal) {
    let what = [
        (Signal::KILL, "SIGKILL"),
        (Signal::STOP, "SIGSTOP"),
        (Signal::CONT, "SIGCONT"),
        (Signal::TERM, "SIGTERM"),
    ]
    .into_iter()
    .find_map(|(s, what)| (s == signal).then_some(what))
    .unwrap_or("a signal");
    eprintln!("faults:   {what} to {name} (pid {pid})");
    if let Some(pid) = rustix::process::Pid::from_raw(pid) {
        let _ = rustix::process::kill_process(pid, signal);
    }
}

/// Flips one random bit of `kind`'s newest checkpoint file in `run_dir`: the learner's networks
/// file (named by its manifest) or the curriculum snapshot. Returns the file, or `None` while
/// there is no checkpoint yet.
fn damage(run_dir: &Path, kind: &str, rng: &mut ChaCha8Rng) -> Result<Option<PathBuf>> {
    let file = if kind == "learner" {
        let dir = run_dir.join("checkpoint");
        let manifest = dir.join("learner.json");
        if !manifest.exists() {
            return Ok(None);
        }
        let doc: Value = serde_json::from_str(
            &std::fs::read_to_string(&manifest)
                .with_context(|| format!("reading {}", manifest.display()))?,
        )
        .with_context(|| format!("parsing {}", manifest.display()))?;
        dir.join(
            doc["networks_file"]
                .as_str()
                .with_context(|| format!("no networks_file in {}", manifest.display()))?,
        )
    } else {
        run_dir.join("curriculum.snapshot.json")
    };
    if !file.exists() {
        return Ok(None);
    }
    let mut bytes = std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
    if bytes.is_empty() {
        bail!("{} is empty", file.display());
    }
    let at = rng.random_range(0..bytes.len());
    bytes[at] ^= 1 << rng.random_range(0..8);
    std::fs::write(&file, bytes).with_context(|| format!("writing {}", file.display()))?;
    Ok(Some(file))
}

/// The results as a Markdown table (for benches/RESULTS.md).
pub fn table(results: &[FaultRun]) -> String {
    let mut s = String::from(
        "| run | fault | process | at (s) | ending | env steps to 90 % | wall s to 90 % | service restarts | rolled back env steps / reports | actor respawns | expired leases | refused reports (duplicates) | shm records lost | refused batches |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in results {
        let times: Vec<String> = r.fault_times_s.iter().map(|t| format!("{t:.0}")).collect();
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} / {} | {} | {} | {} ({}) | {} | {} |\n",
            r.run,
            r.fault,
            r.target,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_disturbed_runs_take_every_fault_with_every_kind_it_applies_to() {
        use Fault::*;
        assert_eq!(
            plan(&[Hang, Corrupt]),
            [
                (Hang, "actor-"),
                (Hang, "eval-actor-"),
                (Hang, "learner"),
                (Hang, "curriculum-server"),
                (Corrupt, "learner"),
                (Corrupt, "curriculum-server"),
            ]
        );
    }

    #[test]
    fn damage_flips_one_bit_of_the_newest_networks_file_or_the_snapshot() {
        let run = tempfile::tempdir().unwrap();
        let dir = run.path().join("checkpoint");
        std::fs::create_dir(&dir).unwrap();
        std::fs::write(
            dir.join("learner.json"),
            r#"{"networks_file": "networks.7.safetensors"}"#,
        )
        .unwrap();
        let original = vec![0x5au8; 64];
        std::fs::write(dir.join("networks.7.safetensors"), &original).unwrap();
        std::fs::write(run.path().join("curriculum.snapshot.json"), &original).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let empty = tempfile::tempdir().unwrap();
        for kind in OWNERS {
            assert_eq!(
                damage(empty.path(), kind, &mut rng).unwrap(),
                None,
                "{kind}"
            );
        }
        for (kind, name) in [
            ("learner", "checkpoint/networks.7.safetensors"),
            ("curriculum-server", "curriculum.snapshot.json"),
        ] {
            let file = damage(run.path(), kind, &mut rng).unwrap().unwrap();
            assert_eq!(file, run.path().join(name));
            let bytes = std::fs::read(&file).unwrap();
            let flipped: u32 = bytes
                .iter()
                .zip(&original)
                .map(|(a, b)| (a ^ b).count_ones())
                .sum();
            assert_eq!(flipped, 1, "{name}");
        }
    }
}
