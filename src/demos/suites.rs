//! `rfcl demos generate --env metaworld/<task>` and `rfcl demos convert --suite adroit`: the demo
//! sources of the MetaWorld and Adroit suites (docs/SUITES.md "Demo files"), written in
//! Python (`python/rfcl_sim/demos.py`) and run here with the venv's Python
//! ([`rfcl_core::python::python_program`]):
//!
//! * `python -m rfcl_sim.demos metaworld --task T -n N --out OUT --seed S`: MetaWorld's scripted
//!   policy from seeds S, S+1, ...; the first N successful episodes;
//! * `python -m rfcl_sim.demos adroit-convert --task T --in IN --out OUT`: the Adroit human demos
//!   a user has (D4RL or Minari HDF5), replayed through the adapter.
//!
//! The tool's per-episode lines drive a progress bar (and are printed: they say how each episode
//! went); its own error message becomes ours; and the file it wrote must load with
//! [`rfcl_core::demo`] and hold what was asked for.
use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rfcl_core::demo::DemoSet;

use super::sim::spawn_python;
use super::{create_parent, path_str};
use rfcl_core::python::python_program;

/// `--env` prefix of MetaWorld tasks.
pub const METAWORLD_PREFIX: &str = "metaworld/";
/// The Adroit tasks: short name, sparse env id (what the demo file and the presets carry).
pub const ADROIT_TASKS: &[(&str, &str)] = &[
    ("door", "AdroitHandDoorSparse-v1"),
    ("pen", "AdroitHandPenSparse-v1"),
    ("relocate", "AdroitHandRelocateSparse-v1"),
];
/// Suites `rfcl demos convert --suite` takes.
const CONVERT_SUITES: &[&str] = &["maniskill3", "adroit"];
/// Lines of the tool's stderr kept for an error message.
const TAIL: usize = 25;

/// `rfcl demos convert`'s options for the suites of this module (flattened into its command).
#[derive(clap::Args, Debug, Clone, Default)]
#[command(after_help = CONVERT_HELP)]
pub struct ConvertArgs {
    /// Suite of the input: maniskill3 or adroit (default: see below).
    #[arg(long, value_name = "SUITE")]
    pub suite: Option<String>,
    /// Adroit task: door, pen, relocate, or an Adroit env id such as AdroitHandDoorSparse-v1
    /// (default: the one task the input's path names).
    #[arg(long, value_name = "TASK")]
    pub task: Option<String>,
    /// Adroit input format (auto: detected from the file).
    #[arg(long, value_name = "FORMAT", value_parser = ["auto", "d4rl", "minari"])]
    pub format: Option<String>,
    /// Adroit: convert only the first N episodes of the input.
    #[arg(long, value_name = "N")]
    pub episodes: Option<u32>,
}

const CONVERT_HELP: &str = "\
Suites:
  maniskill3  a ManiSkill3 trajectory file (.h5 with its .json sidecar, any control and obs
              mode), replayed into pd_joint_delta_pos with state observations.
  adroit      Adroit human demonstrations in D4RL format (door-human-v1.hdf5, pen-human-v1.hdf5,
              relocate-human-v1.hdf5) or Minari format (~/.minari/datasets/D4RL/<task>/human-v2/
              data/main_data.hdf5), replayed through the adapter (docs/SUITES.md, \"Adroit\").

Without --suite: adroit when --task is given, or when the input has no .json sidecar and exactly
one of door, pen, relocate is a word of its path (as in the D4RL and Minari file names above);
otherwise maniskill3. Without --task, the Adroit task is that word of the path.

Examples:
  rfcl demos convert --suite adroit --task door door-human-v1.hdf5 --out runs/demos/door.h5
  rfcl demos convert ~/.minari/datasets/D4RL/pen/human-v2/data/main_data.hdf5 --out pen.h5
  rfcl demos convert trajectory.h5 --out runs/demos/pick_cube.h5";

/// Whether `rfcl demos generate --env ENV` is this module's: `metaworld/<task>` (and `adroit...`,
/// to say that Adroit demos are converted, not generated).
pub fn is_suite_env(env: &str) -> bool {
    let lower = env.to_ascii_lowercase();
    lower.starts_with(METAWORLD_PREFIX) || lower == "metaworld" || lower.starts_with("adroit")
}

/// `rfcl demos generate --env metaworld/<task> -n N --out OUT [--seed S]`.
pub fn generate(env: &str, num: u32, out: &Path, seed: u64) -> Result<()> {
    let lower = env.to_ascii_lowercase();
    if lower.starts_with("adroit") {
        bail!(
            "`rfcl demos generate --env {env}`: Adroit has no demo generator; its demos are the \
             human demonstrations, converted with `rfcl demos convert --suite adroit --task \
             door|pen|relocate FILE --out OUT` (see `rfcl demos convert --help`)"
        );
    }
    let task = lower
        .strip_prefix(METAWORLD_PREFIX)
        .map(metaworld_task)
        .filter(|t| !t.is_empty() && t != "-v3")
        .with_context(|| {
            format!(
                "`rfcl demos generate --env {env}`: expected metaworld/<task>, e.g. \
                 metaworld/pick-place-v3"
            )
        })?;
    create_parent(out)?;
    let bar = bar(u64::from(num), format!("{task}: scripted demos"));
    let mut args: Vec<String> = vec!["metaworld".into(), "--task".into(), task.clone()];
    args.extend(target_args(num, out, seed)?);
    run_demos_tool(&bar, &args, &format!("`rfcl demos generate --env {env}`"))?;
    bar.finish_and_clear();
    let set = load_written(out, &task)?;
    let ok = set.demos.iter().filter(|d| d.succeeded).count();
    if set.demos.len() != num as usize || ok != num as usize {
        bail!(
            "{}: asked for {num} successful demos of {task}, the file has {} episodes ({ok} \
             successful)",
            out.display(),
            set.demos.len()
        );
    }
    report(&set, out, "generated");
    Ok(())
}

/// The demos tool's `-n NUM --out OUT --seed SEED`.
fn target_args(num: u32, out: &Path, seed: u64) -> Result<[String; 6]> {
    Ok([
        "-n".into(),
        num.to_string(),
        "--out".into(),
        path_str(out)?.into(),
        "--seed".into(),
        seed.to_string(),
    ])
}

/// `rfcl demos record --config CFG --policy MODULE:CALLABLE -n N --out OUT [--seed S]
/// [--max-attempts K]`: the first N successful episodes of the user's policy (observation ->
/// action in [-1, 1]) in the env of the run config, from seeds S, S+1, ...
pub fn record(
    config: &Path,
    policy: &str,
    num: u32,
    out: &Path,
    seed: u64,
    max_attempts: Option<u32>,
) -> Result<()> {
    let what = format!("`rfcl demos record --config {}`", config.display());
    let cfg = rfcl_core::config::resolve_file(config, &[])?;
    if cfg.env.suite == rfcl_core::config::Suite::Pointmaze {
        bail!(
            "{what}: PointMaze runs in Rust, not through a Python policy; its demos come from              `rfcl demos generate --env pointmaze`"
        );
    }
    if num == 0 {
        bail!("-n must be at least 1");
    }
    create_parent(out)?;
    let env = &cfg.env;
    let bar = bar(
        u64::from(num),
        format!("{}: recording {policy}", env.env_id),
    );
    let mut args: Vec<String> = vec![
        "record".into(),
        "--suite".into(),
        rfcl_actor::python::suite_name(env.suite),
        "--env-id".into(),
        env.env_id.clone(),
        "--options".into(),
        rfcl_actor::python::env_options(env).to_string(),
        "--policy".into(),
        policy.into(),
    ];
    args.extend(target_args(num, out, seed)?);
    if let Some(k) = max_attempts {
        args.extend(["--max-attempts".into(), k.to_string()]);
    }
    run_demos_tool(&bar, &args, &what)?;
    bar.finish_and_clear();
    let set = load_written(out, &env.env_id)?;
    report(&set, out, "recorded");
    Ok(())
}

/// The MetaWorld task for what follows `metaworld/`: underscores become hyphens (the presets'
/// file names) and `-v3` is added when no version is given.
fn metaworld_task(task: &str) -> String {
    let task = task.trim().replace('_', "-");
    let versioned = task
        .rsplit_once("-v")
        .is_some_and(|(_, v)| !v.is_empty() && v.chars().all(|c| c.is_ascii_digit()));
    if versioned {
        task
    } else {
        format!("{task}-v3")
    }
}

/// Whether `rfcl demos convert INPUT` is this module's (an Adroit file or a suite error) rather
/// than the ManiSkill3 converter's; see [`CONVERT_HELP`].
pub fn handles_convert(input: &Path, args: &ConvertArgs) -> bool {
    match args.suite.as_deref() {
        Some(suite) => {
            suite != "maniskill3"
                || args.task.is_some()
                || args.format.is_some()
                || args.episodes.is_some()
        }
        None => {
            args.task.is_some()
                || (!DemoSet::sidecar_path(input).is_file() && adroit_task_in_path(input).is_ok())
        }
    }
}

/// `rfcl demos convert [--suite adroit] [--task T] IN --out OUT`.
pub fn convert(input: &Path, out: &Path, args: &ConvertArgs) -> Result<()> {
    match args.suite.as_deref() {
        None | Some("adroit") => {}
        Some("maniskill3") => bail!(
            "--task, --format and --episodes are options of Adroit files (--suite adroit); a \
             ManiSkill3 file carries its env in its .json sidecar"
        ),
        Some(other) => bail!(
            "--suite {other}: `rfcl demos convert` converts {} files (MetaWorld demos are \
             generated: `rfcl demos generate --env metaworld/<task>`)",
            CONVERT_SUITES.join(" and ")
        ),
    }
    let (task, env_id) = match args.task.as_deref() {
        Some(t) => adroit_task(t)?,
        None => adroit_task_in_path(input)?,
    };
    if !input.is_file() {
        bail!(
            "{}: no such file (expected an Adroit D4RL or Minari HDF5 file)",
            input.display()
        );
    }
    if !is_hdf5(input)? {
        bail!(
            "{}: not an HDF5 file (expected {env_id}'s human demos as a D4RL or Minari HDF5 file)",
            input.display()
        );
    }
    create_parent(out)?;
    let bar = bar(
        args.episodes.map_or(0, u64::from),
        format!("{env_id}: replaying"),
    );
    let mut tool_args: Vec<String> = vec![
        "adroit-convert".into(),
        "--task".into(),
        task.into(),
        "--in".into(),
        path_str(input)?.into(),
        "--out".into(),
        path_str(out)?.into(),
    ];
    if let Some(format) = &args.format {
        tool_args.extend(["--format".into(), format.clone()]);
    }
    if let Some(n) = args.episodes {
        if n == 0 {
            bail!("--episodes must be at least 1");
        }
        tool_args.extend(["--episodes".into(), n.to_string()]);
    }
    run_demos_tool(
        &bar,
        &tool_args,
        &format!("converting {} ({env_id})", input.display()),
    )?;
    bar.finish_and_clear();
    let set = load_written(out, env_id)?;
    if set.demos.is_empty() {
        bail!("{}: the converter wrote no episodes", out.display());
    }
    report(&set, out, "converted");
    if set.demos.iter().all(|d| !d.succeeded) {
        eprintln!(
            "warning: none of the {} episodes succeeds when replayed in this simulator; a run \
             needs `train.num_demos` successful demos",
            set.demos.len()
        );
    }
    Ok(())
}

/// (short name, sparse env id) for `--task`: a short name or an Adroit env id (sparse or dense).
fn adroit_task(task: &str) -> Result<(&'static str, &'static str)> {
    ADROIT_TASKS
        .iter()
        .find(|(name, id)| {
            task.eq_ignore_ascii_case(name) || task == *id || task == id.replace("Sparse", "")
        })
        .copied()
        .with_context(|| {
            format!(
                "--task {task}: unknown Adroit task; expected one of {} (or the env ids {})",
                names().join(", "),
                ADROIT_TASKS
                    .iter()
                    .map(|(_, id)| *id)
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })
}

/// The one Adroit task whose name is a word of `path` (`door-human-v1.hdf5`,
/// `.../D4RL/door/human-v2/data/main_data.hdf5`).
fn adroit_task_in_path(path: &Path) -> Result<(&'static str, &'static str)> {
    let text = path.to_string_lossy().to_ascii_lowercase();
    let words: Vec<&str> = text.split(|c: char| !c.is_ascii_alphanumeric()).collect();
    let found: Vec<(&str, &str)> = ADROIT_TASKS
        .iter()
        .filter(|(name, _)| words.contains(name))
        .copied()
        .collect();
    match found.as_slice() {
        [one] => Ok(*one),
        [] => bail!(
            "{}: cannot tell the Adroit task from the file's path (none of {} is a word of it); \
             give --task",
            path.display(),
            names().join(", ")
        ),
        _ => bail!(
            "{}: the path names more than one Adroit task ({}); give --task",
            path.display(),
            found.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", ")
        ),
    }
}

/// Whether `path` starts with the HDF5 signature (at byte 0, or after a user block of 512 * 2^k).
fn is_hdf5(path: &Path) -> Result<bool> {
    const SIGNATURE: &[u8] = b"\x89HDF\r\n\x1a\n";
    let mut file =
        std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut head = Vec::new();
    (&mut file)
        .take(8192 + 8)
        .read_to_end(&mut head)
        .with_context(|| format!("reading {}", path.display()))?;
    Ok([0usize, 512, 1024, 2048, 4096, 8192]
        .iter()
        .any(|&at| head.get(at..at + 8) == Some(SIGNATURE)))
}

fn names() -> Vec<&'static str> {
    ADROIT_TASKS.iter().map(|(n, _)| *n).collect()
}

/// Runs `python -u -m rfcl_sim.demos ARGS`; its per-episode stdout lines move and are printed
/// above `bar`. On failure the error is `what`, then the tool's own message (or the tail of its
/// stderr, e.g. a traceback).
fn run_demos_tool(bar: &ProgressBar, args: &[String], what: &str) -> Result<()> {
    let python = python_program();
    let mut child = spawn_python(
        ["-u", "-m", "rfcl_sim.demos"]
            .into_iter()
            .map(String::from)
            .chain(args.iter().cloned()),
        None,
    )
    .with_context(|| what.to_owned())?;
    let stderr = child.stderr.take().expect("piped");
    let err_thread = std::thread::spawn(move || {
        let mut text = String::new();
        let _ = BufReader::new(stderr).read_to_string(&mut text);
        text
    });
    let stdout = child.stdout.take().expect("piped");
    for line in BufReader::new(stdout).lines().map_while(Result::ok) {
        let line = line.trim_end().to_owned();
        if line.trim().is_empty() {
            continue;
        }
        if is_episode_line(&line) {
            bar.inc(u64::from(!line.ends_with("skipped")));
            bar.suspend(|| eprintln!("{line}"));
        } else {
            bar.set_message(line.trim().to_owned());
        }
    }
    let status = child
        .wait()
        .with_context(|| format!("{what}: waiting for {}", python.display()))?;
    let stderr = err_thread.join().unwrap_or_default();
    if status.success() {
        return Ok(());
    }
    bar.finish_and_clear();
    // The tool's own error names the file, task or field and what it expected.
    if let Some(message) = stderr
        .lines()
        .find_map(|l| l.strip_prefix("rfcl_sim.demos: error: "))
    {
        bail!("{what}: {message}");
    }
    let mut tail: VecDeque<&str> = VecDeque::with_capacity(TAIL);
    for line in stderr.lines().filter(|l| !l.trim().is_empty()) {
        if tail.len() == TAIL {
            tail.pop_front();
        }
        tail.push_back(line);
    }
    let tail: Vec<&str> = tail.into_iter().collect();
    bail!(
        "{what}: `{} -m rfcl_sim.demos {}` failed ({status}); its last lines:\n{}",
        python.display(),
        args.join(" "),
        tail.join("\n")
    )
}

/// The generator's `  seed S: ...` and the converter's `  episode K: ...` lines.
fn is_episode_line(line: &str) -> bool {
    let line = line.trim_start();
    ["seed ", "episode "].iter().any(|p| {
        line.strip_prefix(p).is_some_and(|rest| {
            let digits = rest.chars().take_while(char::is_ascii_digit).count();
            digits > 0 && rest[digits..].starts_with(':')
        })
    })
}

/// The demo file the tool wrote, loaded with rfcl's reader, for env `env_id`.
fn load_written(out: &Path, env_id: &str) -> Result<DemoSet> {
    let set = DemoSet::load(out).with_context(|| {
        format!(
            "reading the demos the Python tool wrote to {}",
            out.display()
        )
    })?;
    if set.env_id.as_deref() != Some(env_id) {
        bail!(
            "{}: expected demos of {env_id}, the file says env {}",
            out.display(),
            set.env_id.as_deref().unwrap_or("(none)")
        );
    }
    Ok(set)
}

fn report(set: &DemoSet, out: &Path, verb: &str) {
    let ok = set.demos.iter().filter(|d| d.succeeded).count();
    let lengths: Vec<usize> = set.demos.iter().map(|d| d.len()).collect();
    eprintln!(
        "{verb} {} {} demos ({ok} successful; obs {}, action {}, state {}) into {} (+ {}), \
         lengths {lengths:?}",
        set.demos.len(),
        set.env_id.as_deref().unwrap_or("?"),
        set.obs_dim,
        set.action_dim,
        set.state_dim,
        out.display(),
        DemoSet::sidecar_path(out).display()
    );
}

fn bar(len: u64, message: String) -> ProgressBar {
    let bar = ProgressBar::new(len);
    let template = if len > 0 {
        "{msg} [{bar:30}] {pos}/{len} {elapsed_precise}"
    } else {
        "{spinner} {msg} {pos} episodes {elapsed_precise}"
    };
    bar.set_style(
        ProgressStyle::with_template(template)
            .expect("a valid template")
            .progress_chars("=> "),
    );
    bar.set_message(message);
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    bar
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metaworld_task_names() {
        assert_eq!(metaworld_task("pick-place-v3"), "pick-place-v3");
        assert_eq!(metaworld_task("pick_place"), "pick-place-v3");
        assert_eq!(metaworld_task("stick-pull"), "stick-pull-v3");
        assert!(is_suite_env("metaworld/pick-place-v3") && is_suite_env("MetaWorld/x"));
        assert!(is_suite_env("adroit/door") && !is_suite_env("PickCube-v1"));
    }

    #[test]
    fn adroit_tasks_from_flags_and_paths() {
        assert_eq!(adroit_task("door").unwrap().1, "AdroitHandDoorSparse-v1");
        assert_eq!(adroit_task("AdroitHandPen-v1").unwrap().0, "pen");
        let err = adroit_task("hammer").unwrap_err().to_string();
        assert!(
            err.contains("--task hammer") && err.contains("door, pen, relocate"),
            "{err}"
        );
        assert_eq!(
            adroit_task_in_path(Path::new("/d/relocate-human-v1.hdf5"))
                .unwrap()
                .0,
            "relocate"
        );
        let minari = Path::new("/home/u/.minari/datasets/D4RL/pen/human-v2/data/main_data.hdf5");
        assert_eq!(adroit_task_in_path(minari).unwrap().0, "pen");
        // "pen" inside "openai" is not the word pen.
        assert!(adroit_task_in_path(Path::new("/openai/x.hdf5")).is_err());
        let both = adroit_task_in_path(Path::new("/door/pen.hdf5"))
            .unwrap_err()
            .to_string();
        assert!(
            both.contains("door, pen") && both.contains("--task"),
            "{both}"
        );
    }

    #[test]
    fn episode_lines() {
        assert!(is_episode_line(
            "  seed 3: first success flag at t = 52, T = 63 steps kept"
        ));
        assert!(is_episode_line(
            "  seed 4: no success in 200 steps, skipped"
        ));
        assert!(is_episode_line("  episode 0: T = 12, success at end True"));
        assert!(!is_episode_line(
            "rfcl_sim.demos: 2 scripted demos of pick-place-v3 -> x.h5"
        ));
        assert!(!is_episode_line("wrote 2 episodes (2 successful) to x.h5"));
    }
}
