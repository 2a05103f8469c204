//! Your own task, end to end, as docs/YOUR_TASK.md tells it (the suite `gymnasium`):
//!
//! * WallReach-v0, a task rfcl does not know (examples/your_task/): `rfcl demos record` with its
//!   scripted policy, `rfcl demos inspect --replay`, `rfcl train` of the tutorial's config to its
//!   bar, `rfcl eval`, and the exported policy loaded in Python with NumPy alone
//!   (`rfcl_sim.load_policy`), whose successes on the same held-out seeds are `rfcl eval`'s;
//! * FetchReach-v4 from Gymnasium-Robotics with no code of ours (rfcl's own MuJoCo state), 20,000
//!   env steps (under a minute) in which most demos' frontiers leave their last state;
//! * demos that do not fit the env are refused before any process starts;
//! * a demo state the env refuses is reported by the actor as a failed lease, counted against
//!   its demo, and the run goes on.
//!
//! The env's module is found through `PYTHONPATH`, as the tutorial says.
mod train_support;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use train_support::*;

fn example(file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("examples/your_task")
        .join(file)
}

/// `rfcl ARGS` with the tutorial's PYTHONPATH: (success, stdout + stderr).
fn rfcl_cmd(args: &[&str]) -> (bool, String) {
    rfcl_testkit::child::outcome(
        Command::new(env!("CARGO_BIN_EXE_rfcl"))
            .args(args)
            .env("PYTHONPATH", example("")),
    )
}

/// The tutorial's config `NAME.yml`, and demos recorded with its `NAME:scripted_policy` into
/// `dir/NAME.h5`.
fn recorded_example(dir: &Path, name: &str) -> (PathBuf, PathBuf) {
    let config = example(&format!("{name}.yml"));
    let demos = dir.join(format!("{name}.h5"));
    record(&config, &format!("{name}:scripted_policy"), &demos);
    (config, demos)
}

fn record(config: &Path, policy: &str, out: &Path) {
    let (ok, log) = rfcl_cmd(&[
        "demos",
        "record",
        "--config",
        config.to_str().unwrap(),
        "--policy",
        policy,
        "-n",
        "5",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{log}");
    assert!(log.contains("recorded 5 "), "{log}");
    let (ok, report) = rfcl_cmd(&[
        "demos",
        "inspect",
        out.to_str().unwrap(),
        "--replay",
        "--config",
        config.to_str().unwrap(),
    ]);
    assert!(ok && report.contains("5 of 5 demos pass"), "{report}");
}

/// `rfcl train CONFIG train.dataset_path=DEMOS OVERRIDES` into `dir/run`, which must succeed
/// within `limit`: the run directory and its summary. Every process of the run (and their
/// simulator workers) finds the env's module.
fn train(
    dir: &Path,
    config: &Path,
    demos: &Path,
    overrides: &[&str],
    limit: Duration,
) -> (PathBuf, serde_json::Value) {
    std::env::set_var("PYTHONPATH", example(""));
    let run_dir = dir.join("run");
    let overrides: Vec<String> = overrides.iter().map(|o| o.to_string()).collect();
    let mut training = start_run(
        config,
        demos,
        &overrides,
        &run_dir,
        &dir.join("rfcl.stderr"),
    );
    let status = training.wait(limit);
    assert!(status.success(), "{}", training.stderr());
    let summary = training.summary();
    (run_dir, summary)
}

/// The venv's Python runs `script` with the tutorial's PYTHONPATH (the env's module and
/// rfcl_sim), which must succeed: its stdout.
fn python(script: &str) -> String {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    succeed(
        Command::new(root.join(".venv/bin/python"))
            .args(["-c", script])
            .env(
                "PYTHONPATH",
                format!(
                    "{}:{}",
                    example("").display(),
                    root.join("python").display()
                ),
            ),
    )
}

#[test]
fn the_tutorial_trains_a_task_rfcl_does_not_know() {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let (config, demos) = recorded_example(dir.path(), "wall_reach");

    let (run_dir, summary) = train(dir.path(), &config, &demos, &[], Duration::from_secs(900));
    assert_reached(&summary, 0.9);

    // rfcl eval, then the same held-out seeds with the NumPy policy through the same adapter.
    let episodes = 20;
    let (success, line) = eval_run(&run_dir, episodes);
    assert!(success >= 0.7, "{line}");
    let first_seed: u64 = line
        .split("held-out seeds ")
        .nth(1)
        .and_then(|s| s.split("..").next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no first seed in {line:?}"));
    let script = format!(
        "from rfcl_sim import load_policy\n\
         from rfcl_sim.adapters import make\n\
         policy = load_policy({run:?})\n\
         env = make('gymnasium', 'WallReach-v0', imports=['wall_reach'])\n\
         wins = 0\n\
         for k in range({episodes}):\n\
         \x20   obs = env.reset({first_seed} + k, {{}})\n\
         \x20   for _ in range(env.horizon):\n\
         \x20       obs, success = env.step(policy(obs))\n\
         \x20   wins += success\n\
         print(wins)\n",
        run = run_dir.display().to_string(),
    );
    let wins: u32 = python(&script).trim().parse().unwrap();
    let from_rfcl = (success * f64::from(episodes)).round() as u32;
    // The same deterministic policy and env on the same seeds; the two policies' actions agree
    // to 1e-5 (service_export.rs), so an outcome could only flip on a knife edge.
    assert!(
        wins.abs_diff(from_rfcl) <= 1,
        "numpy policy {wins}/{episodes}, rfcl eval {line}"
    );
}

#[test]
fn a_stock_mujoco_env_trains_with_no_user_code() {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let (config, demos) = recorded_example(dir.path(), "fetch_reach");
    let (_, summary) = train(
        dir.path(),
        &config,
        &demos,
        &[
            "train.steps=20000",
            "sac.eval_freq=10000",
            "service.stop_at_eval_success=null",
        ],
        Duration::from_secs(600),
    );
    assert_eq!(summary["ending"], "budget", "{summary:#}");
    // The reverse curriculum moved: most demos' frontiers left their last state. (Not every one:
    // from a success state a 16-step episode must hold the goal, which one demo in five may not
    // yet do by 20,000 env steps.)
    let demos = summary["demos"].as_array().unwrap();
    assert_eq!(demos.len(), 5);
    let moved = demos
        .iter()
        .filter(|d| d["t"].as_u64().unwrap() + 1 < d["states"].as_u64().unwrap())
        .count();
    assert!(
        moved >= 3,
        "{moved} of 5 frontiers left the end: {demos:#?}"
    );
    assert!(summary["env_steps"].as_u64().unwrap() >= 20000);
}

#[test]
fn a_demo_state_the_env_refuses_is_counted_against_its_demo_and_the_run_goes_on() {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let (config, demos) = recorded_example(dir.path(), "wall_reach");
    // One demo's last 8 states put the point outside the arena: finite numbers, so the file
    // loads, but WallReach's rfcl_set_state refuses them, and stage 1 starts there.
    let script = format!(
        "import h5py\n\
         with h5py.File({file:?}, 'r+') as f:\n\
         \x20   name = sorted(k for k in f if k.startswith('traj_'))[2]\n\
         \x20   pos = f[name + '/env_states/pos']\n\
         \x20   pos[-8:, 0] = 3.0\n\
         \x20   print(name.split('_')[1])\n",
        file = demos.display().to_string(),
    );
    let bad: u64 = python(&script).trim().parse().unwrap();
    // `rfcl demos inspect --config` tries every state in the env and names the first refused.
    let demos_arg = demos.to_str().unwrap();
    let (ok, text) = rfcl_cmd(&["demos", "inspect", demos_arg]);
    assert!(
        ok && text.contains("reset states not checked: pass --config CFG"),
        "{text}"
    );
    let (ok, text) = rfcl_cmd(&[
        "demos",
        "inspect",
        demos_arg,
        "--config",
        config.to_str().unwrap(),
    ]);
    assert!(!ok, "{text}");
    assert!(
        text.contains(&format!("(episode {bad}) state "))
            && text.contains("is not a valid reset state")
            && text.contains("is outside the arena"),
        "{text}"
    );
    // `rfcl train` does not start a simulator to try them: the lease on one fails instead.
    let (_, summary) = train(
        dir.path(),
        &config,
        &demos,
        &["train.steps=6000", "service.stop_at_eval_success=null"],
        Duration::from_secs(600),
    );
    assert_eq!(summary["ending"], "budget", "{summary:#}");
    assert_eq!(summary["actor_respawns"], 0, "no actor died: {summary:#}");
    let failed = summary["failed_resets"].as_u64().unwrap();
    assert!(failed >= 1, "{summary:#}");
    for demo in summary["demos"].as_array().unwrap() {
        let d = &demo["difficulty"];
        if demo["episode_id"] == bad {
            assert_eq!(d["failed_resets"], failed, "{demo:#}");
            let (state, reason) = (&d["last_reset_failure"][0], &d["last_reset_failure"][1]);
            assert!(
                state.as_u64().unwrap() + 8 >= demo["states"].as_u64().unwrap(),
                "{demo:#}"
            );
            assert!(
                reason.as_str().unwrap().contains("is outside the arena"),
                "{demo:#}"
            );
        } else {
            assert_eq!(d["failed_resets"], 0, "{demo:#}");
        }
    }
}

#[test]
fn demos_of_another_env_are_refused_before_anything_starts() {
    require_services();
    let dir = tempfile::tempdir().unwrap();
    let fetch = dir.path().join("fetch_reach.h5");
    record(
        &example("fetch_reach.yml"),
        "fetch_reach:scripted_policy",
        &fetch,
    );
    let run_dir = dir.path().join("run");
    let (ok, text) = rfcl_cmd(&[
        "train",
        example("wall_reach.yml").to_str().unwrap(),
        &format!("train.dataset_path={}", fetch.display()),
        "env.obs_dim=null",
        "env.action_dim=null",
        "--run-dir",
        run_dir.to_str().unwrap(),
    ]);
    assert!(!ok, "{text}");
    assert!(
        text.contains("the demos do not fit env 'WallReach-v0' of suite 'gymnasium': the demos have obs 16 and action 4 values, the env 6 and 2"),
        "{text}"
    );
    assert!(!run_dir.exists(), "nothing was started");
}
