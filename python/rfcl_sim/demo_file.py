"""Reading and writing rfcl demo files from Python (the format of core/src/demo/mod.rs, spec 6.1).

A demo file is an HDF5 file with one group ``traj_<episode_id>`` per demo:

* ``actions`` ``[T, A]`` float32, ``obs`` ``[T+1, D]`` float32, ``success`` ``[T]`` bool
  (``success[t]`` is the flag after action t);
* ``env_states/<field>`` ``[T+1, k]`` float32, one dataset per state field (kind ``field`` of the
  adapter's state layout), created with tracked link order so that the Rust reader sees the
  fields in the adapter's order (it falls back to name order for untracked groups);

plus a JSON sidecar with the same base name (``demos.h5`` -> ``demos.json``): ``env_info``
(``env_id``, ``env_kwargs``, ``max_episode_steps``, and what made the file) and ``episodes[]`` with
``episode_id``, ``reset_kwargs`` (``seed``, ``options``: applied before a state is set, spec 2.4),
``episode_seed``, ``elapsed_steps`` and the episode's ``success`` (also as ``info.success``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


class DemoFileError(Exception):
    """A demo file that cannot be written or read; the message names the file and the field."""


@dataclass
class Trajectory:
    """One demo: T actions, T + 1 observations and states, T success flags."""

    episode_id: int
    obs: np.ndarray
    actions: np.ndarray
    success: np.ndarray
    states: np.ndarray
    seed: int | None = None
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])

    @property
    def succeeded(self) -> bool:
        """The episode's outcome (spec 6.1 skips failed episodes): success at its last step."""
        return bool(self.length > 0 and self.success[-1])


def sidecar_path(path: Path) -> Path:
    """The JSON sidecar of a demo file: same base name, extension ``.json`` (as the Rust reader)."""
    return Path(path).with_suffix(".json")


def write(path: Path, env_info: dict[str, Any], layout: list[tuple[str, str, int]],
          trajectories: list[Trajectory]) -> None:
    """Writes ``trajectories`` to ``path`` and its sidecar. ``layout`` is the adapter's state layout
    (only ``field`` entries); ``env_info`` must name ``env_id``."""
    import h5py

    path = Path(path)
    _validate(path, env_info, layout, trajectories)
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        for traj in trajectories:
            g = f.create_group(f"traj_{traj.episode_id}")
            g.create_dataset("actions", data=np.asarray(traj.actions, dtype=np.float32))
            g.create_dataset("obs", data=np.asarray(traj.obs, dtype=np.float32))
            g.create_dataset("success", data=np.asarray(traj.success, dtype=bool))
            states = g.create_group("env_states", track_order=True)
            offset = 0
            for name, _, n in layout:
                column = np.asarray(traj.states[:, offset:offset + n], dtype=np.float32)
                states.create_dataset(name, data=column)
                offset += n
    episodes = []
    for traj in trajectories:
        entry: dict[str, Any] = {
            "episode_id": traj.episode_id,
            "reset_kwargs": {"seed": traj.seed, "options": traj.options},
            "elapsed_steps": traj.length,
            "success": traj.succeeded,
            "info": {"success": traj.succeeded},
        }
        if traj.seed is not None:
            entry["episode_seed"] = traj.seed
        episodes.append(entry)
    text = json.dumps({"env_info": env_info, "episodes": episodes}, indent=2)
    sidecar_path(path).write_text(text + "\n")


def read(path: Path) -> tuple[dict[str, Any], list[tuple[str, str, int]], list[Trajectory]]:
    """Reads any demo file rfcl reads (core/src/demo/mod.rs): ``env_info``, the state layout and
    the trajectories by ascending episode id. ``env_states`` may be named fields (what
    :func:`write` and the MetaWorld/Adroit sources write), ManiSkill3's groups ``actors/<name>``
    and ``articulations/<name>`` (what ``rfcl demos generate`` and ``convert`` write for
    ManiSkill3; entries ``actors/...`` first, then ``articulations/...``, each group in its link
    order, as the Rust reader flattens them), or one flat dataset (ManiSkill2)."""
    import h5py

    path = Path(path)
    side = sidecar_path(path)
    try:
        meta = json.loads(side.read_text())
    except (OSError, ValueError) as e:
        raise DemoFileError(f"{side}: cannot read the JSON sidecar of {path}: {e}") from e
    resets = {e["episode_id"]: e.get("reset_kwargs", {}) for e in meta.get("episodes", [])}
    layout: list[tuple[str, str, int]] | None = None
    trajectories = []
    with h5py.File(path, "r") as f:
        names = sorted((n for n in f if n.startswith("traj_")), key=lambda n: int(n[5:]))
        for name in names:
            g = f[name]
            episode_id = int(name[5:])
            if "env_states" not in g:
                raise DemoFileError(f"{path}: {name} has no env_states")
            leaves = _state_leaves(path, name, g["env_states"])
            this_layout = [(leaf, kind, int(values.shape[1])) for leaf, kind, values in leaves]
            if layout is None:
                layout = this_layout
            elif this_layout != layout:
                raise DemoFileError(f"{path}: {name}/env_states has entries {this_layout}, the "
                                    f"first trajectory has {layout}")
            reset = resets.get(episode_id)
            if reset is None:
                raise DemoFileError(f"{side}: no episodes[] entry for {name}")
            trajectories.append(Trajectory(
                episode_id=episode_id,
                obs=_rows(g["obs"][()]).astype(np.float32),
                actions=_rows(g["actions"][()]).astype(np.float32),
                success=np.asarray(g["success"][()]).astype(bool).reshape(-1),
                states=np.concatenate([values for _, _, values in leaves], axis=1)
                .astype(np.float32),
                seed=reset.get("seed", reset.get("episode_seed")),
                options=reset.get("options") or {},
            ))
    if layout is None:
        raise DemoFileError(f"{path}: no traj_<id> groups")
    return meta["env_info"], layout, trajectories


def _rows(values: np.ndarray) -> np.ndarray:
    """A 1-D dataset is one column."""
    values = np.asarray(values)
    return values.reshape(-1, 1) if values.ndim == 1 else values


def _state_leaves(path: Path, traj: str, states: Any) -> list[tuple[str, str, np.ndarray]]:
    """``env_states`` as ``(entry name, kind, [T+1, k] values)`` in layout order."""
    import h5py

    if isinstance(states, h5py.Dataset):
        return [("env_states", "flat", _rows(states[()]))]
    groups = [k for k in ("actors", "articulations") if k in states]
    if groups:
        leaves = []
        for group in groups:
            kind = "actor" if group == "actors" else "articulation"
            for entity, values in states[group].items():  # link order
                if not isinstance(values, h5py.Dataset):
                    raise DemoFileError(f"{path}: {traj}/env_states/{group}/{entity} is not a "
                                        "dataset")
                leaves.append((f"{group}/{entity}", kind, _rows(values[()])))
        return leaves
    leaves = []
    for field_name, values in states.items():  # creation order: the group tracks it
        if not isinstance(values, h5py.Dataset):
            raise DemoFileError(f"{path}: {traj}/env_states/{field_name} is a group; expected "
                                "named fields, or ManiSkill3's actors/ and articulations/")
        leaves.append((field_name, "field", _rows(values[()])))
    return leaves


def _validate(path: Path, env_info: dict[str, Any], layout: list[tuple[str, str, int]],
              trajectories: list[Trajectory]) -> None:
    if not env_info.get("env_id"):
        raise DemoFileError(f"{path}: env_info needs an env_id")
    if not trajectories:
        raise DemoFileError(f"{path}: no trajectories to write")
    bad = [name for name, kind, _ in layout
           if kind != "field" or not name or name.split("/")[0] in ("actors", "articulations")]
    if bad:
        raise DemoFileError(f"{path}: state entries {bad} are not named fields (kind 'field')")
    state_dim = sum(n for _, _, n in layout)
    seen = set()
    for traj in trajectories:
        where = f"{path}: traj_{traj.episode_id}"
        if traj.episode_id in seen:
            raise DemoFileError(f"{where} appears twice")
        seen.add(traj.episode_id)
        t = traj.length
        expected = {
            "obs": (t + 1, trajectories[0].obs.shape[1]),
            "actions": (t, trajectories[0].actions.shape[1]),
            "success": (t,),
            "states": (t + 1, state_dim),
        }
        for what, shape in expected.items():
            got = np.shape(getattr(traj, what))
            if got != shape:
                raise DemoFileError(f"{where}: {what} has shape {got}, expected {shape} "
                                    f"(T = {t} actions)")
