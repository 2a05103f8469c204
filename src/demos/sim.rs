//! `rfcl demos generate --env <ManiSkill3 task>` and `rfcl demos convert`: demos with simulator
//! states for the Python suites, made by ManiSkill's own tools (spec 7.1, "Demos"):
//!
//! 1. `python -m mani_skill.examples.motionplanning.panda.run -e ENV -n S+N --only-count-success
//!    -b physx_cpu` plans S+N successful episodes under `pd_joint_pos` (seeds 0, 1, ...), recorded
//!    with their env states (generate only; the planner always starts at seed 0, so `--seed S`
//!    plans the first S too and drops them);
//! 2. `python -m mani_skill.trajectory.replay_trajectory -c pd_joint_delta_pos -o state
//!    --save-traj -b physx_cpu` replays them in the run's control mode with state observations,
//!    saving the replays that succeed;
//! 3. the first N successful episodes with seed ≥ S are written to `--out` (+ its JSON sidecar) with
//!    core's writer, which `rfcl demos inspect` and the services read.
//!
//! A seed that gives no demo (the planner finds no plan, or its plan fails, about 1 in 4 seeds of
//! PegInsertionSide and PlugCharger; or the plan does not replay to a success in the run's control
//! mode) is skipped and never written; the seeds skipped are counted and named on stderr
//! ([`Failures`]), and the written demos' seeds are listed.
//!
//! Both tools run in a temporary directory (ManiSkill writes beside its input), with the venv's
//! Python ([`python_program`]); their progress drives one progress bar, and when one fails the
//! error carries the last lines of its output.
use std::collections::VecDeque;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use super::{create_parent, path_str};

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rfcl_core::demo::{Demo, DemoSet};
use rfcl_core::python::{python_program, PYTHON_ENV};

/// The control mode the presets train in (spec 7.1).
pub const CONTROL_MODE: &str = "pd_joint_delta_pos";
/// ManiSkill's CPU simulation backend.
pub const SIM_BACKEND: &str = "physx_cpu";
/// Lines of a tool's output kept for an error message.
const TAIL: usize = 25;
/// Motion planning rounds before giving up when replays in the target control mode fail.
const ATTEMPTS: u32 = 3;

/// The envs ManiSkill 3.0.1 has motion-planning solutions for
/// (`mani_skill.examples.motionplanning.panda.run`).
pub const MOTION_PLANNED: &[&str] = &[
    "PickCube-v1",
    "StackCube-v1",
    "PegInsertionSide-v1",
    "PlugCharger-v1",
    "PushCube-v1",
    "PullCube-v1",
    "LiftPegUpright-v1",
    "PullCubeTool-v1",
    "PlaceSphere-v1",
    "StackPyramid-v1",
    "DrawTriangle-v1",
    "DrawSVG-v1",
];

/// Starts [`python_program`] with `args` (in `dir` when given), unbuffered, stdin closed, stdout
/// and stderr piped.
pub fn spawn_python<S: AsRef<std::ffi::OsStr>>(
    args: impl IntoIterator<Item = S>,
    dir: Option<&Path>,
) -> Result<std::process::Child> {
    let python = python_program();
    let mut command = Command::new(&python);
    command
        .args(args)
        .env("PYTHONUNBUFFERED", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    if let Some(dir) = dir {
        command.current_dir(dir);
    }
    command.spawn().with_context(|| {
        format!(
            "starting {} (set {PYTHON_ENV} to the venv's python, e.g. .venv/bin/python)",
            python.display()
        )
    })
}

/// Whether `env` names a ManiSkill3 task `rfcl demos generate` can plan.
pub fn is_maniskill_env(env: &str) -> bool {
    MOTION_PLANNED.contains(&env)
}

/// `rfcl demos generate --env ENV -n N --out OUT --seed S` for a ManiSkill3 task: the first N
/// successful episodes from motion-planning seeds S, S+1, ...
pub fn generate(env: &str, num: u32, out: &Path, seed: u64) -> Result<()> {
    let skipped = u32::try_from(seed)
        .ok()
        .filter(|s| s.checked_add(num).is_some())
        .with_context(|| format!("--seed {seed}: too large (the planner plans seeds 0..seed+n)"))?;
    let tmp = temp_dir_near(out)?;
    let bar = bar(u64::from(skipped + num));
    let mut planned = skipped + num;
    let mut failures = Failures::default();
    for attempt in 1..=ATTEMPTS {
        bar.set_position(0);
        bar.set_length(u64::from(planned));
        bar.set_message(format!("{env}: motion planning"));
        let record = tmp.path().join(format!("plan{attempt}"));
        run_tool(
            &bar,
            Tool::Plan,
            &[
                "-m",
                "mani_skill.examples.motionplanning.panda.run",
                "-e",
                env,
                "-n",
                &planned.to_string(),
                "--only-count-success",
                "-b",
                SIM_BACKEND,
                "--record-dir",
                path_str(&record)?,
                "--traj-name",
                "trajectory",
            ],
            tmp.path(),
        )?;
        let raw = record
            .join(env)
            .join("motionplanning")
            .join("trajectory.h5");
        let plans = planned_seeds(&raw)?;
        let converted = replay(&bar, &raw, u64::from(planned), tmp.path())?;
        let mut set = DemoSet::load(&converted)
            .with_context(|| format!("reading ManiSkill's replay {}", converted.display()))?;
        set.demos = from_seed(set.demos, seed);
        let replayed: Vec<u64> = set
            .demos
            .iter()
            .filter(|d| d.succeeded)
            .filter_map(|d| d.reset.seed)
            .collect();
        failures.add(&plans, &replayed, seed);
        let ok = set.demos.iter().filter(|d| d.succeeded).count() as u32;
        if ok >= num {
            bar.finish_and_clear();
            failures.report(env);
            return write_first(&set, num, out, "generated");
        }
        // Some plans did not survive the change of controller: plan more and try again.
        tracing::info!(
            attempt,
            planned,
            successful = ok,
            "fewer successful replays than asked; planning more"
        );
        planned = skipped + num + 2 * (num - ok);
    }
    bar.finish_and_clear();
    failures.report(env);
    bail!(
        "after {ATTEMPTS} rounds of motion planning, fewer than {num} episodes of {env} replayed \
         successfully in {CONTROL_MODE}"
    )
}

/// The seeds that gave no demo, each counted once over all planning rounds (the planner starts
/// at seed 0 every round, so a round repeats the earlier rounds' seeds).
#[derive(Debug, Default, PartialEq)]
struct Failures {
    /// Seeds the planner tried and kept no episode of: no plan, or a plan that did not succeed.
    plans: std::collections::BTreeSet<u64>,
    /// Seeds whose successful plan did not replay to a success in [`CONTROL_MODE`].
    replays: std::collections::BTreeSet<u64>,
}

impl Failures {
    /// Adds one round: `planned` are the seeds of the planner's successful episodes (the seeds
    /// below their largest that are missing failed), `replayed` those that replayed successfully.
    /// Seeds below `first` were never asked for and are left out.
    fn add(&mut self, planned: &[u64], replayed: &[u64], first: u64) {
        let Some(&last) = planned.iter().max() else {
            return;
        };
        self.plans
            .extend((first..last).filter(|s| !planned.contains(s)));
        self.replays.extend(
            planned
                .iter()
                .filter(|&&s| s >= first && !replayed.contains(&s)),
        );
    }

    /// One line per kind of failure, on stderr: a skipped seed is never written.
    fn report(&self, env: &str) {
        if !self.plans.is_empty() {
            eprintln!(
                "{env}: the motion planner gave no successful episode for {} seed(s) {:?}: skipped, not written",
                self.plans.len(),
                self.plans
            );
        }
        if !self.replays.is_empty() {
            eprintln!(
                "{env}: {} planned episode(s) did not replay to a success in {CONTROL_MODE}, \
                 seed(s) {:?}: skipped, not written",
                self.replays.len(),
                self.replays
            );
        }
    }
}

/// The reset seeds of the episodes the planner kept, from the JSON sidecar beside `raw`.
fn planned_seeds(raw: &Path) -> Result<Vec<u64>> {
    let sidecar = DemoSet::sidecar_path(raw);
    let text = std::fs::read_to_string(&sidecar)
        .with_context(|| format!("reading the planner's sidecar {}", sidecar.display()))?;
    let meta: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("{} is not JSON", sidecar.display()))?;
    let episodes = meta["episodes"]
        .as_array()
        .map(Vec::as_slice)
        .unwrap_or(&[]);
    episodes
        .iter()
        .map(|e| {
            e["reset_kwargs"]["seed"]
                .as_u64()
                .or_else(|| e["episode_seed"].as_u64())
                .with_context(|| {
                    format!(
                        "{}: episode {} has no reset seed",
                        sidecar.display(),
                        e["episode_id"]
                    )
                })
        })
        .collect()
}

/// `rfcl demos convert IN --out OUT`: a ManiSkill3 trajectory file (any control and obs mode, with
/// env states and its JSON sidecar) replayed into `pd_joint_delta_pos` with state observations;
/// the successful episodes are kept.
pub fn convert(input: &Path, out: &Path) -> Result<()> {
    let sidecar = DemoSet::sidecar_path(input);
    if !input.is_file() {
        bail!("{}: no such file", input.display());
    }
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&sidecar).with_context(|| {
            format!(
                "reading {} (ManiSkill writes a JSON sidecar beside every trajectory file; \
                 `rfcl demos convert` needs its env_info and reset seeds)",
                sidecar.display()
            )
        })?)
        .with_context(|| format!("{} is not JSON", sidecar.display()))?;
    let env_id = meta["env_info"]["env_id"]
        .as_str()
        .with_context(|| format!("{}: env_info.env_id is missing", sidecar.display()))?;
    let episodes = meta["episodes"].as_array().map_or(0, Vec::len) as u64;
    if episodes == 0 {
        bail!("{}: episodes[] is empty", sidecar.display());
    }
    // ManiSkill writes its replay beside the input: work on a copy.
    let tmp = temp_dir_near(out)?;
    let copy = tmp.path().join("input.h5");
    std::fs::copy(input, &copy).with_context(|| format!("copying {}", input.display()))?;
    std::fs::copy(&sidecar, DemoSet::sidecar_path(&copy))
        .with_context(|| format!("copying {}", sidecar.display()))?;
    let bar = bar(episodes);
    let converted = replay(&bar, &copy, episodes, tmp.path())?;
    bar.finish_and_clear();
    let set = DemoSet::load(&converted)
        .with_context(|| format!("reading ManiSkill's replay {}", converted.display()))?;
    let ok = set.demos.iter().filter(|d| d.succeeded).count() as u32;
    if ok == 0 {
        bail!(
            "none of the {episodes} episodes of {} ({env_id}) replays successfully in {CONTROL_MODE}",
            input.display()
        );
    }
    write_first(&set, ok, out, "converted")
}

/// The demos whose reset seed is at least `seed` (all of them for seed 0, seedless ones included).
fn from_seed(demos: Vec<Demo>, seed: u64) -> Vec<Demo> {
    if seed == 0 {
        return demos;
    }
    demos
        .into_iter()
        .filter(|d| d.reset.seed.is_some_and(|s| s >= seed))
        .collect()
}

/// Replays `raw` into the target control mode with state observations; the output's path.
fn replay(bar: &ProgressBar, raw: &Path, episodes: u64, dir: &Path) -> Result<PathBuf> {
    bar.set_position(0);
    bar.set_length(episodes);
    bar.set_message(format!("replaying in {CONTROL_MODE}, state observations"));
    run_tool(
        bar,
        Tool::Replay,
        &[
            "-m",
            "mani_skill.trajectory.replay_trajectory",
            "--traj-path",
            path_str(raw)?,
            "-c",
            CONTROL_MODE,
            "-o",
            "state",
            "--save-traj",
            "-b",
            SIM_BACKEND,
        ],
        dir,
    )?;
    let name = format!(
        "{}.state.{CONTROL_MODE}.{SIM_BACKEND}.h5",
        raw.file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("trajectory")
    );
    let converted = raw.with_file_name(name);
    if !converted.is_file() {
        bail!(
            "replay_trajectory finished but wrote no {}",
            converted.display()
        );
    }
    Ok(converted)
}

/// Writes the first `num` successful demos of `set` to `out`, with their sidecar.
fn write_first(set: &DemoSet, num: u32, out: &Path, verb: &str) -> Result<()> {
    let mut chosen = set
        .select(num as usize, false, 0)
        .with_context(|| format!("selecting {num} successful demos"))?;
    chosen.path = out.to_path_buf();
    create_parent(out)?;
    chosen.write(out)?;
    let lengths: Vec<usize> = chosen.demos.iter().map(|d| d.len()).collect();
    let seeds: Vec<String> = chosen
        .demos
        .iter()
        .map(|d| d.reset.seed.map_or("none".into(), |s| s.to_string()))
        .collect();
    eprintln!(
        "{verb} {num} successful {} demos ({}, state observations) into {} (+ {}), lengths \
         {lengths:?}, seeds [{}]",
        chosen.env_id.as_deref().unwrap_or("?"),
        chosen.control_mode.as_deref().unwrap_or(CONTROL_MODE),
        out.display(),
        DemoSet::sidecar_path(out).display(),
        seeds.join(", ")
    );
    Ok(())
}

#[derive(Clone, Copy)]
enum Tool {
    Plan,
    Replay,
}

/// Runs the venv's Python with `args` in `dir`; its output (tqdm lines) moves `bar`.
fn run_tool(bar: &ProgressBar, tool: Tool, args: &[&str], dir: &Path) -> Result<()> {
    let python = python_program();
    let shown = format!("{} {}", python.display(), args.join(" "));
    let mut child = spawn_python(args, Some(dir))?;
    // stdout on a thread, stderr here; both feed the tail and the progress.
    let stdout = child.stdout.take().expect("piped");
    let out_thread = std::thread::spawn(move || {
        let mut text = String::new();
        let _ = std::io::BufReader::new(stdout).read_to_string(&mut text);
        text
    });
    let mut tail = VecDeque::with_capacity(TAIL);
    let mut stderr = child.stderr.take().expect("piped");
    let mut buf = [0u8; 4096];
    let mut pending = Vec::new();
    loop {
        let n = stderr.read(&mut buf).unwrap_or(0);
        if n == 0 {
            break;
        }
        pending.extend_from_slice(&buf[..n]);
        // tqdm redraws with '\r'; logs end with '\n'.
        while let Some(at) = pending.iter().position(|&b| b == b'\r' || b == b'\n') {
            let line = String::from_utf8_lossy(&pending[..at]).trim().to_owned();
            pending.drain(..=at);
            if line.is_empty() {
                continue;
            }
            if let Some(done) = progress(tool, &line) {
                bar.set_position(done);
            } else {
                push_tail(&mut tail, line);
            }
        }
    }
    let status = child.wait().context("waiting for the tool")?;
    let text = out_thread.join().unwrap_or_default();
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        push_tail(&mut tail, line.trim().to_owned());
    }
    if !status.success() {
        let tail: Vec<String> = tail.into_iter().collect();
        bail!(
            "`{shown}` failed ({status}); its last lines:\n{}",
            tail.join("\n")
        );
    }
    Ok(())
}

fn push_tail(tail: &mut VecDeque<String>, line: String) {
    if tail.len() == TAIL {
        tail.pop_front();
    }
    tail.push_back(line);
}

/// Progress from one tqdm line: planning shows `| k/N [`, replays name `Replaying traj_k`.
fn progress(tool: Tool, line: &str) -> Option<u64> {
    match tool {
        Tool::Plan => {
            let after = line.split('|').nth(2)?.trim_start();
            let (done, _) = after.split_once('/')?;
            done.parse().ok()
        }
        Tool::Replay => {
            let rest = line.split("Replaying traj_").nth(1)?;
            let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
            digits.parse().ok()
        }
    }
}

fn bar(len: u64) -> ProgressBar {
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} {elapsed_precise}")
            .expect("a valid template")
            .progress_chars("=> "),
    );
    bar
}

/// A temporary directory on the output's file system (ManiSkill's files are moved out of it).
fn temp_dir_near(out: &Path) -> Result<tempfile::TempDir> {
    let dir = out
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    tempfile::Builder::new()
        .prefix(".rfcl-demos-")
        .tempdir_in(dir)
        .with_context(|| format!("creating a temporary directory in {}", dir.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tqdm_lines_give_progress() {
        let plan = "proc_id: 0:  50%|█████     | 1/2 [00:00<00:00,  3.07it/s]";
        assert_eq!(progress(Tool::Plan, plan), Some(1));
        assert_eq!(
            progress(Tool::Plan, "Motion Planning Running on PickCube-v1"),
            None
        );
        let replay = "Replaying traj_3:  43%|████▎     | 32/74 [00:00<00:00, 319.15step/s]";
        assert_eq!(progress(Tool::Replay, replay), Some(3));
        assert_eq!(progress(Tool::Replay, "Replayed 2 episodes"), None);
    }

    #[test]
    fn failed_seeds_are_the_gaps_below_the_last_plan_and_the_plans_that_did_not_replay() {
        let mut failures = Failures::default();
        // Planned 0, 1, 3, 4, 7 (2, 5, 6 failed); 4 did not replay.
        failures.add(&[0, 1, 3, 4, 7], &[0, 1, 3, 7], 0);
        // A second round repeats them and goes on: 8 fails, 9 plans and replays.
        failures.add(&[0, 1, 3, 4, 7, 9], &[0, 1, 3, 7, 9], 0);
        assert_eq!(
            failures.plans.iter().copied().collect::<Vec<_>>(),
            [2, 5, 6, 8]
        );
        assert_eq!(failures.replays.iter().copied().collect::<Vec<_>>(), [4]);
        // Seeds below --seed were never asked for.
        let mut from_three = Failures::default();
        from_three.add(&[0, 2, 4, 6], &[0, 2, 6], 3);
        assert_eq!(from_three.plans.iter().copied().collect::<Vec<_>>(), [3, 5]);
        assert_eq!(from_three.replays.iter().copied().collect::<Vec<_>>(), [4]);
        assert_eq!(Failures::default(), {
            let mut none = Failures::default();
            none.add(&[], &[], 0);
            none
        });
    }

    #[test]
    fn from_seed_keeps_the_demos_at_or_after_it() {
        let demo = |seed| Demo {
            episode_id: 0,
            obs_dim: 0,
            action_dim: 0,
            state_dim: 0,
            obs: vec![],
            actions: vec![],
            success: vec![],
            env_states: vec![],
            succeeded: true,
            success_source: rfcl_core::demo::SuccessSource::Steps,
            reset: rfcl_core::demo::ResetArgs {
                seed,
                ..Default::default()
            },
        };
        let seeds = |demos: Vec<Demo>| demos.iter().map(|d| d.reset.seed).collect::<Vec<_>>();
        let all = || vec![demo(Some(0)), demo(Some(2)), demo(None), demo(Some(5))];
        assert_eq!(
            seeds(from_seed(all(), 0)),
            [Some(0), Some(2), None, Some(5)]
        );
        assert_eq!(seeds(from_seed(all(), 2)), [Some(2), Some(5)]);
        assert_eq!(seeds(from_seed(all(), 6)), []);
    }
}
