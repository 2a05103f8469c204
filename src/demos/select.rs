//! `rfcl demos select`: a demo file without the demos a run found stalled, or with only its best K
//! (docs/ALGORITHM.md 2.10). The run's per-demo view comes from its curriculum server while the run
//! is going (over gRPC, with the run's token), else from its summary.json.
use std::cmp::Ordering;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use rfcl_core::demo::DemoSet;
use rfcl_core::run_state::{DemoBar, RunState};
use rfcl_proto::auth::{authenticated, Token};
use rfcl_proto::v1::curriculum_client::CurriculumClient;

/// Where a run's per-demo view came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    /// The run's curriculum server, which answered at this address.
    Live(String),
    /// The run's summary.json.
    Summary(PathBuf),
}

/// The demos of the run in `run_dir`: live from its curriculum server if it still answers, else
/// from its summary.json.
pub fn run_demos(run_dir: &Path) -> Result<(Vec<DemoBar>, Source)> {
    if let Some((view, addr)) = live_view(run_dir) {
        return Ok((view.demos, Source::Live(addr)));
    }
    let path = run_dir.join("summary.json");
    let text = std::fs::read_to_string(&path).with_context(|| {
        format!(
            "{}: no summary (and no running curriculum server in {}/processes.json); \
             pass the directory of a run that `rfcl train` started",
            path.display(),
            run_dir.display()
        )
    })?;
    let summary: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let demos: Vec<DemoBar> = serde_json::from_value(summary["demos"].clone())
        .with_context(|| format!("{}: field `demos`", path.display()))?;
    if demos.is_empty() {
        bail!(
            "{}: field `demos` is empty: the run ended before its curriculum server reported \
             any demo (or an older rfcl wrote it)",
            path.display()
        );
    }
    Ok((demos, Source::Summary(path)))
}

/// The view of the run's curriculum server, if processes.json names one that answers.
fn live_view(run_dir: &Path) -> Option<(RunState, String)> {
    let text = std::fs::read_to_string(run_dir.join("processes.json")).ok()?;
    let processes: serde_json::Value = serde_json::from_str(&text).ok()?;
    let addr = processes["curriculum"].as_str()?.to_string();
    let token = Token::read_file(Path::new(processes["token_file"].as_str()?)).ok()?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .ok()?;
    runtime.block_on(async {
        let channel = tonic::transport::Channel::from_shared(addr.clone())
            .ok()?
            .connect_timeout(Duration::from_secs(2))
            .connect()
            .await
            .ok()?;
        let mut client = CurriculumClient::new(authenticated(channel, &token))
            .max_decoding_message_size(64 << 20);
        let view = crate::train::fetch_run_state(&mut client).await?;
        Some((view, addr))
    })
}

/// Why a demo was dropped.
#[derive(Debug, Clone, PartialEq)]
pub struct Dropped {
    pub episode_id: u64,
    pub reason: String,
}

/// Which of the run's demos to keep (by episode id, in the run's order) and why the others go:
/// every stalled demo goes; with `best`, only the best `best` by [`rank`] stay.
pub fn choose(demos: &[DemoBar], best: Option<usize>) -> (Vec<u64>, Vec<Dropped>) {
    let mut ranked: Vec<&DemoBar> = demos.iter().collect();
    ranked.sort_by(|a, b| rank(a, b));
    let mut keep = Vec::new();
    let mut dropped = Vec::new();
    for (place, d) in ranked.into_iter().enumerate() {
        let x = &d.difficulty;
        if x.stalled {
            let cell = x
                .cell
                .map(|[r, c]| format!(", maze cell ({r}, {c})"))
                .unwrap_or_default();
            dropped.push(Dropped {
                episode_id: d.episode_id,
                reason: format!(
                    "stalled at state {} of {}{cell}: no frontier move for {} env steps while \
                     other demos advanced ({} of {} frontier episodes succeeded)",
                    d.t,
                    d.states,
                    x.env_steps_since_move,
                    (x.frontier_success_rate * x.frontier_episodes as f64).round(),
                    x.frontier_episodes
                ),
            });
        } else if best.is_some_and(|k| keep.len() >= k) {
            dropped.push(Dropped {
                episode_id: d.episode_id,
                reason: format!(
                    "not among the best {}: ranked {} ({}, {:.2} states per 10k env steps)",
                    best.unwrap_or_default(),
                    place + 1,
                    if d.solved { "solved" } else { "not solved" },
                    x.speed
                ),
            });
        } else {
            keep.push(d.episode_id);
        }
    }
    // Keep the run's order.
    let keep = demos
        .iter()
        .map(|d| d.episode_id)
        .filter(|id| keep.contains(id))
        .collect();
    (keep, dropped)
}

/// The order of `rfcl demos select --best` (docs/ALGORITHM.md 2.10): demos that are not stalled
/// first, then solved before unsolved, then the faster frontier (states per 10k env steps) first.
pub fn rank(a: &DemoBar, b: &DemoBar) -> Ordering {
    a.difficulty
        .stalled
        .cmp(&b.difficulty.stalled)
        .then(b.solved.cmp(&a.solved))
        .then(b.difficulty.speed.total_cmp(&a.difficulty.speed))
        .then(a.demo.cmp(&b.demo))
}

/// `rfcl demos select FILE --run RUN_DIR --out OUT [--best K]`.
pub fn select(file: &Path, run_dir: &Path, out: &Path, best: Option<usize>) -> Result<()> {
    if best == Some(0) {
        bail!("--best must be at least 1");
    }
    let (demos, source) = run_demos(run_dir)?;
    match &source {
        Source::Live(addr) => eprintln!("the run's curriculum server at {addr} answered"),
        Source::Summary(path) => eprintln!("read the run's demos from {}", path.display()),
    }
    let (keep, dropped) = choose(&demos, best);
    super::check::refuse_if_it_crashes_the_reader(file)?;
    let set = DemoSet::load(file).with_context(|| format!("reading {}", file.display()))?;
    let missing: Vec<u64> = demos
        .iter()
        .map(|d| d.episode_id)
        .filter(|id| !set.demos.iter().any(|e| e.episode_id == *id))
        .collect();
    if !missing.is_empty() {
        bail!(
            "{}: has no episode {missing:?} of the run in {}: pass the demo file the run trained on",
            file.display(),
            run_dir.display()
        );
    }
    if keep.is_empty() {
        bail!(
            "every demo of the run would be dropped ({}); nothing written",
            dropped
                .iter()
                .map(|d| format!("episode {}: {}", d.episode_id, d.reason))
                .collect::<Vec<_>>()
                .join("; ")
        );
    }
    let mut selected = set.clone();
    selected.demos = keep
        .iter()
        .map(|id| {
            set.demos
                .iter()
                .find(|e| e.episode_id == *id)
                .cloned()
                .expect("checked above")
        })
        .collect();
    selected
        .write(out)
        .with_context(|| format!("writing {}", out.display()))?;
    for d in &dropped {
        println!("dropped episode {}: {}", d.episode_id, d.reason);
    }
    println!(
        "kept {} of the run's {} demos (episodes {keep:?}); wrote {} (+ {})",
        keep.len(),
        demos.len(),
        out.display(),
        DemoSet::sidecar_path(out).display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rfcl_core::run_state::DemoDifficulty;

    fn bar(demo: u32, episode_id: u64, solved: bool, speed: f64, stalled: bool) -> DemoBar {
        DemoBar {
            demo,
            episode_id,
            t: if solved { 0 } else { 40 },
            states: 100,
            frontier_success_rate: 0.0,
            solved,
            difficulty: DemoDifficulty {
                speed,
                stalled,
                frontier_episodes: 10,
                frontier_success_rate: 0.1,
                env_steps_since_move: 60_000,
                cell: Some([10, 6]),
                ..Default::default()
            },
        }
    }

    #[test]
    fn stalled_demos_go_and_best_keeps_the_solved_and_fastest_in_the_runs_order() {
        let demos = [
            bar(0, 10, true, 2.0, false),
            bar(1, 11, false, 9.0, true),
            bar(2, 12, true, 5.0, false),
            bar(3, 13, false, 3.0, false),
        ];
        let (keep, dropped) = choose(&demos, None);
        assert_eq!(keep, vec![10, 12, 13]);
        assert_eq!(dropped.len(), 1);
        assert_eq!(dropped[0].episode_id, 11);
        assert!(
            dropped[0]
                .reason
                .starts_with("stalled at state 40 of 100, maze cell (10, 6)"),
            "{}",
            dropped[0].reason
        );
        // Ranked: 12 (solved, 5.0), 10 (solved, 2.0), 13 (unsolved), 11 (stalled).
        let (keep, dropped) = choose(&demos, Some(2));
        assert_eq!(keep, vec![10, 12]);
        let ids: Vec<u64> = dropped.iter().map(|d| d.episode_id).collect();
        assert_eq!(ids, vec![13, 11]);
        assert!(
            dropped[0].reason.contains("ranked 3"),
            "{}",
            dropped[0].reason
        );
    }
}
