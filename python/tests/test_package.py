"""The ``rfcl_sim`` package as a researcher installs it (``pip install ./python``): its version is
the workspace's, and its demo-file reader reads every form of file rfcl writes or reads."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from rfcl_sim import demo_file

ROOT = Path(__file__).resolve().parents[2]


def test_the_package_version_is_the_workspaces():
    cargo = (ROOT / "Cargo.toml").read_text()
    workspace = re.search(r'\[workspace\.package\][^\[]*?version = "([^"]+)"', cargo).group(1)
    pyproject = (ROOT / "python" / "pyproject.toml").read_text()
    package = re.search(r'^version = "([^"]+)"', pyproject, re.M).group(1)
    assert package == workspace


def _write_ms3(path: Path, steps: int) -> dict[str, np.ndarray]:
    """A ManiSkill3-form demo file: env_states/actors/<name> and articulations/<name> groups."""
    import h5py

    rng = np.random.default_rng(0)
    parts = {"actors/cube": rng.normal(size=(steps + 1, 13)),
             "actors/goal": rng.normal(size=(steps + 1, 13)),
             "articulations/arm": rng.normal(size=(steps + 1, 13 + 2 * 2))}
    with h5py.File(path, "w") as f:
        g = f.create_group("traj_0")
        g["obs"] = rng.normal(size=(steps + 1, 5)).astype(np.float32)
        g["actions"] = rng.normal(size=(steps, 2)).astype(np.float32)
        g["success"] = np.arange(steps) == steps - 1
        states = g.create_group("env_states", track_order=True)
        for group in ("actors", "articulations"):
            sub = states.create_group(group, track_order=True)
            for name, values in parts.items():
                if name.startswith(group):
                    sub[name.split("/")[1]] = values.astype(np.float32)
    path.with_suffix(".json").write_text(json.dumps({
        "env_info": {"env_id": "PickCube-v1", "max_episode_steps": 50},
        "episodes": [{"episode_id": 0, "reset_kwargs": {"seed": 7}, "success": True}],
    }))
    return parts


def test_maniskill3_files_read_with_their_actor_and_articulation_entries(tmp_path):
    path = tmp_path / "pick_cube.h5"
    parts = _write_ms3(path, steps=4)
    env_info, layout, trajs = demo_file.read(path)
    assert env_info["env_id"] == "PickCube-v1"
    assert layout == [("actors/cube", "actor", 13), ("actors/goal", "actor", 13),
                      ("articulations/arm", "articulation", 17)]
    (traj,) = trajs
    assert traj.seed == 7 and traj.length == 4 and traj.succeeded
    expected = np.concatenate([parts[k] for k in ("actors/cube", "actors/goal",
                                                  "articulations/arm")], axis=1)
    np.testing.assert_array_equal(traj.states, expected.astype(np.float32))


def test_flat_states_read_as_one_entry(tmp_path):
    import h5py

    path = tmp_path / "ms2.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("traj_3")
        g["obs"] = np.zeros((3, 4), np.float32)
        g["actions"] = np.zeros((2, 1), np.float32)
        g["success"] = np.array([False, True])
        g["env_states"] = np.ones((3, 9), np.float32)
    path.with_suffix(".json").write_text(json.dumps({
        "env_info": {"env_id": "PickCube-v0"},
        "episodes": [{"episode_id": 3, "reset_kwargs": {"seed": 1}}],
    }))
    _, layout, trajs = demo_file.read(path)
    assert layout == [("env_states", "flat", 9)]
    assert trajs[0].actions.shape == (2, 1) and trajs[0].states.shape == (3, 9)
