"""Demo sources (rfcl_sim.demos): scripted MetaWorld demos and the Adroit converter, checked by
replaying them through the adapters and, when the release binary is built, with the Rust reader
(`rfcl demos inspect`)."""
import json
import subprocess
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest

from rfcl_sim import adapters, demo_file, demos

warnings.filterwarnings("ignore")

RFCL = Path(__file__).resolve().parents[2] / "target" / "release" / "rfcl"


def rust_inspect(path):
    """`rfcl demos inspect` output, or a skip when the release binary is not built."""
    if not RFCL.exists():
        pytest.skip(f"{RFCL} is not built")
    done = subprocess.run([str(RFCL), "demos", "inspect", str(path)], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout


def replay_from_first_state(env, traj):
    """What rfcl does with a demo: reset(seed, options), set_state(states[0]), then the actions."""
    env.reset(traj.seed, traj.options)
    obs = [env.set_state(traj.states[0])]
    flags = []
    for action in traj.actions:
        o, success = env.step(action)
        obs.append(o)
        flags.append(success)
    return np.stack(obs), np.asarray(flags)


# MetaWorld scripted demos -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pick_place_demos(tmp_path_factory):
    out = tmp_path_factory.mktemp("mw") / "pick_place.h5"
    demos.generate_metaworld("pick-place-v3", 3, out, log=lambda *_: None)
    return out


def test_scripted_metaworld_demos_replay_to_success(pick_place_demos):
    env_info, layout, trajs = demo_file.read(pick_place_demos)
    assert env_info["env_id"] == "pick-place-v3" and env_info["max_episode_steps"] == 200
    env = adapters.make("metaworld", "pick-place-v3")
    try:
        assert layout == env.state_layout()
        assert [t.seed for t in trajs] == [0, 1, 2]
        for traj in trajs:
            assert traj.succeeded and traj.success.any()
            obs, flags = replay_from_first_state(env, traj)
            assert np.array_equal(flags, traj.success)
            np.testing.assert_allclose(obs, traj.obs, atol=1e-6)
            # A later state restores too (a reverse-curriculum start).
            mid = traj.length // 2
            env.reset(traj.seed, traj.options)
            np.testing.assert_allclose(env.set_state(traj.states[mid]), traj.obs[mid], atol=1e-6)
    finally:
        env.close()


def test_scripted_demos_load_in_rust(pick_place_demos):
    report = rust_inspect(pick_place_demos)
    assert "episodes: 3 (3 successful)" in report
    assert "dims: obs 39, action 4, env_state 62" in report
    names = [line.split()[-2] for line in report.splitlines() if "(field)" in line]
    assert names == ["qpos", "qvel", "mocap_pos", "mocap_quat", "rand_vec", "prev_frame"]


def test_metaworld_cli_reports_a_task_without_policy(tmp_path, capsys):
    assert demos.main(["metaworld", "--task", "nope-v3", "-n", "1",
                       "--out", str(tmp_path / "x.h5")]) == 1
    assert "no scripted policy for task 'nope-v3'" in capsys.readouterr().err


# Adroit converter: source files written in the D4RL and Minari formats --------------------------


def record_episode(env, seed, steps, rng, initial=None):
    """Rows of a source file: obs, actions and the state before each action, plus the final obs."""
    obs = env.reset(seed, {})
    if initial is not None:
        obs = env.set_state(initial)
    rows = {"obs": [obs], "actions": [], "states": [env.get_state()], "success": [False]}
    action = np.zeros(env.action_dim)
    for _ in range(steps):
        action = np.clip(0.8 * action + 0.3 * rng.normal(size=env.action_dim), -1, 1)
        obs, success = env.step(action)
        rows["actions"].append(action.astype(np.float32))
        rows["obs"].append(obs)
        rows["states"].append(env.get_state())
        rows["success"].append(success)
    return {k: np.stack(v) for k, v in rows.items()}


def write_d4rl(path, env, episodes):
    """A D4RL-format file: episodes concatenated, one row per action, `timeouts` on last rows."""
    fields = env._split(episodes[0]["states"][0])
    with h5py.File(path, "w") as f:
        f["observations"] = np.concatenate([e["obs"][:-1] for e in episodes])
        f["actions"] = np.concatenate([e["actions"] for e in episodes])
        n = len(f["actions"])
        f["rewards"] = np.zeros(n, dtype=np.float32)
        f["terminals"] = np.zeros(n, dtype=bool)
        timeouts = np.zeros(n, dtype=bool)
        timeouts[np.cumsum([len(e["actions"]) for e in episodes]) - 1] = True
        f["timeouts"] = timeouts
        for name in fields:
            rows = [env._split(s)[name] for e in episodes for s in e["states"][:-1]]
            if name in ("obj_pos", "target_pos"):
                rows = [np.array([0.1, 0.2, 0.3])] * n  # D4RL issue 196: not the real positions
            f[f"infos/{name}"] = np.stack(rows)


def write_minari(path, env, episodes, with_initial_state=True):
    """A Minari-format main_data.hdf5: one group per episode, reset options as attributes."""
    with h5py.File(path, "w") as f:
        for k, e in enumerate(episodes):
            g = f.create_group(f"episode_{k}")
            g.attrs["id"] = k
            g.attrs["total_steps"] = len(e["actions"])
            g["observations"] = e["obs"].astype(np.float64)
            g["actions"] = e["actions"]
            g["rewards"] = np.zeros(len(e["actions"]))
            g["terminations"] = np.zeros(len(e["actions"]), dtype=bool)
            g["truncations"] = np.zeros(len(e["actions"]), dtype=bool)
            g["infos/success"] = e["success"]
            if with_initial_state:
                for name, value in env._split(e["states"][0]).items():
                    g.attrs[f"options/initial_state_dict/{name}"] = value.astype(np.float64)


def check_conversion(out, env, episodes, from_d4rl):
    env_info, layout, trajs = demo_file.read(out)
    assert env_info["env_id"] == env.env_id and layout == env.state_layout()
    assert len(trajs) == len(episodes)
    for k, (traj, source) in enumerate(zip(trajs, episodes)):
        assert traj.seed == k and traj.length == len(source["actions"])
        assert set(traj.options["initial_state_dict"]) == {n for n, _, _ in layout}
        np.testing.assert_allclose(traj.states, source["states"], atol=1e-5)
        np.testing.assert_allclose(traj.obs[:-1] if from_d4rl else traj.obs,
                                   source["obs"][:-1] if from_d4rl else source["obs"], atol=1e-5)
        np.testing.assert_array_equal(traj.success, source["success"][1:])
        # The converted demo replays through the adapter as rfcl restores it.
        obs, flags = replay_from_first_state(env, traj)
        np.testing.assert_array_equal(flags, traj.success)
        np.testing.assert_allclose(obs, traj.obs, atol=1e-6)
    return trajs


@pytest.mark.parametrize("task", ["door", "relocate"])
def test_d4rl_file_converts_and_replays(tmp_path, task):
    env = adapters.make("adroit", task)
    try:
        rng = np.random.default_rng(0)
        initial = None
        if task == "door":  # start the first episode with the door open: a successful demo
            env.reset(0, {})
            initial = env.get_state()
            initial[env._env.door_hinge_addrs] = 1.5
        episodes = [record_episode(env, 0, 12, rng, initial), record_episode(env, 1, 9, rng)]
        src = tmp_path / f"{task}-human-v1.hdf5"
        write_d4rl(src, env, episodes)
        out = tmp_path / f"{task}.h5"
        trajs = demos.convert_adroit(task, src, out, log=lambda *_: None)
        check_conversion(out, env, episodes, from_d4rl=True)
        if task == "door":
            assert trajs[0].succeeded
    finally:
        env.close()
    report = rust_inspect(out)
    assert f"episodes: 2 ({1 if task == 'door' else 0} successful)" in report


def test_minari_file_converts_and_replays(tmp_path):
    env = adapters.make("adroit", "pen")
    try:
        rng = np.random.default_rng(1)
        episodes = [record_episode(env, s, 8, rng) for s in (3, 4)]
        src = tmp_path / "main_data.hdf5"
        write_minari(src, env, episodes)
        out = tmp_path / "pen.h5"
        assert demos.main(["adroit-convert", "--task", "pen", "--in", str(src),
                           "--out", str(out)]) == 0
        check_conversion(out, env, episodes, from_d4rl=False)
    finally:
        env.close()
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["env_info"]["env_id"] == "AdroitHandPenSparse-v1"
    assert sidecar["env_info"]["max_episode_steps"] == 100
    assert "dims: obs 45, action 24, env_state 64" in rust_inspect(out)


def test_minari_file_without_initial_states_is_refused(tmp_path):
    env = adapters.make("adroit", "door")
    try:
        episodes = [record_episode(env, 0, 4, np.random.default_rng(2))]
        src = tmp_path / "main_data.hdf5"
        write_minari(src, env, episodes, with_initial_state=False)
    finally:
        env.close()
    with pytest.raises(demos.DemoSourceError, match="episode_0 carries no initial state"):
        demos.convert_adroit("door", src, tmp_path / "out.h5", log=lambda *_: None)


def test_converter_names_a_file_of_another_task(tmp_path):
    env = adapters.make("adroit", "door")
    try:
        episodes = [record_episode(env, 0, 3, np.random.default_rng(3))]
        src = tmp_path / "door-human-v1.hdf5"
        write_d4rl(src, env, episodes)
    finally:
        env.close()
    with pytest.raises(demos.DemoSourceError, match="D4RL file lacks 'infos/desired_orien'"):
        demos.convert_adroit("pen", src, tmp_path / "out.h5", log=lambda *_: None)
