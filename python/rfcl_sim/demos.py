"""Demo sources for MetaWorld, Adroit and your own policy, written in rfcl's demo format
(:mod:`rfcl_sim.demo_file`).

``python -m rfcl_sim.demos record --suite S --env-id E --options JSON --policy M:F -n N --out FILE``
    (what ``rfcl demos record --config CFG --policy M:F`` runs): your policy ``F`` of module ``M``
    (a callable from an observation to an action in [-1, 1]) in the env a run config describes,
    episodes recorded as the MetaWorld ones below, the first N successful ones kept.

``python -m rfcl_sim.demos metaworld --task pick-place-v3 -n 5 --out FILE``
    Rolls out MetaWorld's scripted policy (``metaworld.policies``) from seeds 0, 1, 2, ... through
    the adapter and keeps the first N successful episodes. Each episode starts with
    ``reset(seed)`` and then ``set_state(get_state())``, exactly what rfcl does to restore a demo
    state, so that replaying the file from its first state reproduces it step for step. An episode
    ends ``--post-success-steps`` steps after its first success step (capped by the horizon) and is
    cut back to its last success step, so every kept demo ends in a success state.

``python -m rfcl_sim.demos adroit-convert --task door --in FILE --out FILE``
    Converts the Adroit human demonstrations (25 per task, from the DAPG project) that a user
    already has, in one of two formats:

    * **D4RL** (``door-human-v1.hdf5``, ``pen-human-v1.hdf5``, ``relocate-human-v1.hdf5``, from
      ``http://rail.eecs.berkeley.edu/datasets/offline_rl/hand_dapg_v1/``; the ``d4rl`` package
      caches them in ``~/.d4rl/datasets/``): the episodes concatenated along the first axis:
      ``observations [N, D]``, ``actions [N, A]``, ``rewards [N]``, ``terminals [N]``,
      ``timeouts [N]`` (true on an episode's last row) and ``infos/qpos``, ``infos/qvel`` and the
      task's fields (``infos/door_body_pos``, ``infos/desired_orien``; Relocate's
      ``infos/obj_pos`` and ``infos/target_pos`` are the same for every episode in these files,
      D4RL issue 196, so its ball and target positions are recovered from the observations).
    * **Minari** (``minari download D4RL/door/human-v2``, read from
      ``~/.minari/datasets/D4RL/door/human-v2/data/main_data.hdf5``): one group ``episode_<k>``
      per episode with ``observations [T+1, D]``, ``actions [T, A]``, ``rewards``,
      ``terminations``, ``truncations [T]``, ``infos/success [T+1]``; the initial state is read
      from the episode's reset options (attributes ``options/initial_state_dict/<field>``) or from
      per-step states (``infos/state/<field>`` or ``state/<field>`` datasets) when present.

    The states the curriculum resets to must be states of *this* simulator, and neither format
    stores the state after an episode's last action, so every episode is replayed from its
    initial state with its recorded actions: observations, states and success flags in the output
    all come from the replay (the largest difference to the file's observations is printed; the
    human demos were recorded with an older MuJoCo, so they may drift). Each episode resets with
    seed = its index and ``options.initial_state_dict`` = its initial state (spec 7.4).
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import demo_file
from .adapters.base import AdapterError
from .demo_file import Trajectory

#: Default number of steps recorded after an episode's first success step.
POST_SUCCESS_STEPS = 10


class DemoSourceError(Exception):
    """A demo source that cannot be used; the message names the file, the field and why."""


# MetaWorld scripted demos ------------------------------------------------------------------------


def scripted_policy(task: str) -> Any:
    """MetaWorld's scripted policy for ``task``."""
    from metaworld.policies import ENV_POLICY_MAP

    if task not in ENV_POLICY_MAP:
        raise DemoSourceError(f"metaworld: no scripted policy for task '{task}'; tasks with one: "
                              f"{', '.join(sorted(ENV_POLICY_MAP))}")
    return ENV_POLICY_MAP[task]()


def metaworld_episode(adapter: Any, policy: Any, seed: int, post_success_steps: int
                      ) -> Trajectory | None:
    """One scripted episode from ``seed``; ``None`` when it never succeeds within the horizon."""
    return policy_episode(adapter, policy.get_action, seed, post_success_steps)


def policy_episode(adapter: Any, act: Callable[[np.ndarray], Any], seed: int,
                   post_success_steps: int) -> Trajectory | None:
    """One episode of ``act`` (observation -> action in [-1, 1]) from ``seed``, started from the
    float32 state a replay starts from; ``None`` when it never succeeds within the horizon."""
    adapter.reset(seed, {})
    state = adapter.get_state()
    obs = adapter.set_state(state)  # start from the float32 state a replay starts from
    observations, states, actions, flags = [obs], [state], [], []
    first_success = None
    for t in range(adapter.horizon):
        action = np.clip(np.asarray(act(obs), dtype=np.float32).reshape(-1), -1.0, 1.0)
        obs, success = adapter.step(action)
        observations.append(obs)
        states.append(adapter.get_state())
        actions.append(action)
        flags.append(success)
        if success and first_success is None:
            first_success = t
        if first_success is not None and t >= first_success + post_success_steps:
            break
    if first_success is None:
        return None
    end = max(i for i, s in enumerate(flags) if s) + 1  # cut back to the last success step
    return Trajectory(
        episode_id=-1,
        obs=np.stack(observations[:end + 1]),
        actions=np.stack(actions[:end]),
        success=np.asarray(flags[:end], dtype=bool),
        states=np.stack(states[:end + 1]),
        seed=seed,
        options={},
    )


def successful_episodes(adapter: Any, act: Callable[[np.ndarray], Any], n: int, first_seed: int,
                        attempts: int, post_success_steps: int, log
                        ) -> tuple[list[Trajectory], int]:
    """Episodes of ``act`` from seeds ``first_seed``, ``first_seed + 1``, ... until ``n`` succeed
    or ``attempts`` were tried, each said in one line; the successful ones (episode ids 0, 1, ...)
    and the next seed."""
    kept: list[Trajectory] = []
    seed = first_seed
    while len(kept) < n and seed < first_seed + attempts:
        traj = policy_episode(adapter, act, seed, post_success_steps)
        if traj is None:
            log(f"  seed {seed}: no success in {adapter.horizon} steps, skipped")
        else:
            traj.episode_id = len(kept)
            kept.append(traj)
            log(f"  seed {seed}: first success flag at t = {int(np.argmax(traj.success))}, "
                f"T = {traj.length} steps kept")
        seed += 1
    return kept, seed


def generate_metaworld(task: str, n: int, out: Path, first_seed: int = 0,
                       max_attempts: int | None = None,
                       post_success_steps: int = POST_SUCCESS_STEPS,
                       max_episode_steps: int | None = None, log=print) -> list[Trajectory]:
    """Writes ``n`` successful scripted demos of ``task`` to ``out``; seeds run from
    ``first_seed`` up, at most ``max_attempts`` episodes (default 4n)."""
    from .adapters import metaworld

    if n < 1:
        raise DemoSourceError(f"metaworld: -n must be at least 1, got {n}")
    policy = scripted_policy(task)
    adapter = metaworld.make(task, max_episode_steps=max_episode_steps)
    attempts = max_attempts if max_attempts is not None else 4 * n
    try:
        kept, seed = successful_episodes(adapter, policy.get_action, n, first_seed, attempts,
                                         post_success_steps, log)
        if len(kept) < n:
            raise DemoSourceError(
                f"metaworld: only {len(kept)} of {attempts} scripted episodes of {task} succeeded "
                f"(seeds {first_seed}..{seed - 1}), {n} wanted; raise --max-attempts"
            )
        env_info = {
            "env_id": task,
            "suite": "metaworld",
            "env_kwargs": {},
            "max_episode_steps": adapter.horizon,
            "source": f"metaworld.policies.{type(policy).__name__} (rfcl_sim.demos metaworld)",
        }
        demo_file.write(out, env_info, adapter.state_layout(), kept)
    finally:
        adapter.close()
    return kept


# Your own policy ---------------------------------------------------------------------------------


def load_callable(spec: str) -> Callable[..., Any]:
    """``module:callable`` (after the config's ``env.imports`` are imported)."""
    from .adapters.base import entry_point

    try:
        return entry_point("--policy", spec)
    except AdapterError as e:
        raise DemoSourceError(str(e)) from e


def record(suite: str, env_id: str, options: dict[str, Any], policy: str, n: int, out: Path,
           first_seed: int = 0, max_attempts: int | None = None,
           post_success_steps: int = POST_SUCCESS_STEPS, log=print) -> list[Trajectory]:
    """Writes ``n`` successful episodes of ``policy`` (``module:callable``: observation -> action
    in [-1, 1]) in the env the run config describes (``suite``, ``env_id``, its env ``options``)
    to ``out``; seeds run from ``first_seed`` up, at most ``max_attempts`` episodes (default
    4n). Each episode is recorded like the scripted MetaWorld demos: from the float32 state a
    replay starts from, cut back to its last success step."""
    from . import adapters

    if n < 1:
        raise DemoSourceError(f"record: -n must be at least 1, got {n}")
    adapter = adapters.make(suite, env_id, **options)
    try:
        act = load_callable(policy)
        attempts = max_attempts if max_attempts is not None else 4 * n
        kept, seed = successful_episodes(adapter, act, n, first_seed, attempts,
                                         post_success_steps, log)
        if len(kept) < n:
            raise DemoSourceError(
                f"record: only {len(kept)} of {seed - first_seed} episodes of {policy} in "
                f"{env_id} succeeded (seeds {first_seed}..{seed - 1}), {n} wanted; raise "
                "--max-attempts or fix the policy"
            )
        env_info = {
            "env_id": env_id,
            "suite": suite,
            "env_kwargs": dict(options.get("env_kwargs") or {}),
            "max_episode_steps": adapter.horizon,
            "source": f"{policy} (rfcl demos record)",
        }
        demo_file.write(out, env_info, adapter.state_layout(), kept)
    finally:
        adapter.close()
    return kept


# Adroit human demos ------------------------------------------------------------------------------


@dataclass
class SourceEpisode:
    """One episode read from a source file, before replay."""

    index: int
    observations: np.ndarray  # [T or T+1, D]: D4RL has one row per action, Minari one more
    actions: np.ndarray  # [T, A]
    initial_state: dict[str, np.ndarray]  # fields of the env's set_env_state dict
    relocate_world: bool = False  # Relocate obj/target positions are world positions from obs


def detect_format(path: Path) -> str:
    """``"d4rl"`` or ``"minari"``, from the file's top-level keys."""
    import h5py

    with h5py.File(path, "r") as f:
        keys = set(f.keys())
    if {"observations", "actions"} <= keys:
        return "d4rl"
    if any(k.startswith("episode_") for k in keys):
        return "minari"
    raise DemoSourceError(
        f"{path}: neither a D4RL file (top-level 'observations', 'actions', 'timeouts', 'infos/') "
        f"nor a Minari file (groups 'episode_<k>'); found keys {sorted(keys)[:10]}"
    )


def read_d4rl(path: Path, task: str) -> list[SourceEpisode]:
    """The episodes of a D4RL Adroit file (module docs)."""
    import h5py

    with h5py.File(path, "r") as f:
        def get(key: str) -> np.ndarray:
            if key not in f:
                raise DemoSourceError(f"{path}: D4RL file lacks '{key}'")
            return f[key][()]

        obs, actions = get("observations"), get("actions")
        n = obs.shape[0]
        ends = np.zeros(n, dtype=bool)
        for key in ("timeouts", "terminals"):
            if key in f:
                ends |= f[key][()].astype(bool).reshape(-1)
        ends[-1] = True
        qpos, qvel = get("infos/qpos"), get("infos/qvel")
        fields = {"door": ["door_body_pos"], "pen": ["desired_orien"], "relocate": []}[task]
        extra = {k: get(f"infos/{k}") for k in fields}
    for key, arr in [("actions", actions), ("infos/qpos", qpos), ("infos/qvel", qvel),
                     *[(f"infos/{k}", v) for k, v in extra.items()]]:
        if arr.shape[0] != n:
            raise DemoSourceError(f"{path}: '{key}' has {arr.shape[0]} rows, 'observations' {n}")
    episodes, start = [], 0
    for end in np.flatnonzero(ends):
        initial = {"qpos": qpos[start], "qvel": qvel[start]}
        initial.update({k: v[start] for k, v in extra.items()})
        episodes.append(SourceEpisode(
            index=len(episodes),
            observations=obs[start:end + 1],
            actions=actions[start:end + 1],
            initial_state=initial,
            relocate_world=task == "relocate",
        ))
        start = end + 1
    return episodes


def read_minari(path: Path, task: str, field_names: list[str]) -> list[SourceEpisode]:
    """The episodes of a Minari Adroit file (module docs); ``field_names`` are the task's state
    fields."""
    import h5py

    episodes = []
    with h5py.File(path, "r") as f:
        names = sorted((k for k in f if k.startswith("episode_")), key=lambda k: int(k[8:]))
        for name in names:
            g = f[name]
            for key in ("observations", "actions"):
                if key not in g:
                    raise DemoSourceError(f"{path}: {name} lacks '{key}'")
            initial = _minari_initial_state(path, name, g, field_names)
            episodes.append(SourceEpisode(
                index=int(name[8:]),
                observations=g["observations"][()],
                actions=g["actions"][()],
                initial_state=initial,
            ))
    if not episodes:
        raise DemoSourceError(f"{path}: no episode_<k> groups")
    return episodes


def _minari_initial_state(path: Path, name: str, g: Any, field_names: list[str]
                          ) -> dict[str, np.ndarray]:
    prefix = "options/initial_state_dict/"
    from_attrs = {k[len(prefix):]: np.asarray(v) for k, v in g.attrs.items()
                  if k.startswith(prefix)}
    if all(k in from_attrs for k in field_names):
        return {k: from_attrs[k] for k in field_names}
    for group in ("infos/state", "state"):
        if group in g and all(k in g[group] for k in field_names):
            return {k: g[group][k][0] for k in field_names}
    raise DemoSourceError(
        f"{path}: {name} carries no initial state: expected attributes "
        f"'{prefix}<field>' or datasets 'infos/state/<field>' for {field_names}. Minari files "
        "written without reset options cannot be replayed; convert the D4RL file "
        "(<task>-human-v1.hdf5) instead"
    )


def convert_adroit(task: str, src: Path, out: Path, fmt: str = "auto",
                   max_episodes: int | None = None, log=print) -> list[Trajectory]:
    """Converts the Adroit demos in ``src`` (module docs) to a demo file ``out``; returns the
    replayed trajectories."""
    from .adapters import adroit

    src = Path(src)
    if not src.is_file():
        raise DemoSourceError(f"{src}: no such file")
    env_id = adroit.canonical_id(task)
    adapter = adroit.make(env_id)
    task = adapter.task
    fields = [name for name, _, _ in adapter.state_layout()]
    fmt = detect_format(src) if fmt == "auto" else fmt
    if fmt == "d4rl":
        episodes = read_d4rl(src, task)
    elif fmt == "minari":
        episodes = read_minari(src, task, fields)
    else:
        raise DemoSourceError(f"unknown --format '{fmt}': expected auto, d4rl or minari")
    if max_episodes is not None:
        episodes = episodes[:max_episodes]
    trajectories = []
    try:
        for ep in episodes:
            if ep.actions.ndim != 2 or ep.actions.shape[1] != adapter.action_dim:
                raise DemoSourceError(f"{src}: episode {ep.index} has actions of shape "
                                      f"{ep.actions.shape}, {env_id} takes {adapter.action_dim}")
            if ep.observations.shape[1] != adapter.obs_dim:
                raise DemoSourceError(f"{src}: episode {ep.index} has {ep.observations.shape[1]}-"
                                      f"value observations, {env_id} has {adapter.obs_dim}")
            initial = dict(ep.initial_state)
            if ep.relocate_world:
                initial["obj_pos"], initial["target_pos"] = relocate_positions(
                    adapter, initial["qpos"], ep.observations[0])
            try:
                state0 = adapter.state_from_dict(initial, f"episode {ep.index} initial state")
            except AdapterError as e:
                raise DemoSourceError(f"{src}: {e}") from e
            traj = replay(adapter, ep.index, state0, ep.actions)
            n = min(len(traj.obs), len(ep.observations))
            drift = float(np.abs(traj.obs[:n] - ep.observations[:n]).max())
            first = int(np.argmax(traj.success)) if traj.success.any() else None
            log(f"  episode {ep.index}: T = {traj.length}, success at end {traj.succeeded}, "
                f"first success flag at t = {first}, max |obs - file obs| {drift:.3g}")
            trajectories.append(traj)
        env_info = {
            "env_id": env_id,
            "suite": "adroit",
            "env_kwargs": {},
            "max_episode_steps": adapter.horizon,
            "source": f"{src.name} ({fmt}), replayed by rfcl_sim.demos adroit-convert",
        }
        demo_file.write(out, env_info, adapter.state_layout(), trajectories)
    finally:
        adapter.close()
    return trajectories


def relocate_positions(adapter: Any, qpos: np.ndarray, obs0: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Relocate's ball model position and target position for an episode whose first observation
    is ``obs0`` with joint positions ``qpos``: the observation holds palm - ball (values 30:33) and
    ball - target (36:39), and the palm follows from ``qpos``."""
    palm = adapter.palm_pos(qpos)
    obj_world = palm - np.asarray(obs0[30:33], dtype=np.float64)
    target_world = obj_world - np.asarray(obs0[36:39], dtype=np.float64)
    return adapter.relocate_model_pos(qpos, obj_world, target_world)


def replay(adapter: Any, index: int, state0: np.ndarray, actions: np.ndarray) -> Trajectory:
    """Replays ``actions`` from ``state0`` (reset with seed ``index`` and the state as
    ``options.initial_state_dict``), recording observations, states and success flags."""
    options = {"initial_state_dict": adapter.state_to_dict(state0)}
    obs = adapter.reset(index, options)
    observations, states, flags = [obs], [adapter.get_state()], []
    acts = np.asarray(actions, dtype=np.float32)
    for a in acts:
        obs, success = adapter.step(np.clip(a, -1.0, 1.0))
        observations.append(obs)
        states.append(adapter.get_state())
        flags.append(success)
    return Trajectory(
        episode_id=index,
        obs=np.stack(observations),
        actions=np.clip(acts, -1.0, 1.0),
        success=np.asarray(flags, dtype=bool),
        states=np.stack(states),
        seed=index,
        options=options,
    )


# Command line ------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rfcl_sim.demos", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    mw = sub.add_parser("metaworld", help="scripted MetaWorld demos")
    mw.add_argument("--task", required=True, help="MetaWorld v3 task, e.g. pick-place-v3")
    mw.add_argument("-n", type=int, default=5, help="successful demos to keep (default 5)")
    mw.add_argument("--out", required=True, type=Path, help="demo file to write (.h5)")
    mw.add_argument("--seed", type=int, default=0, help="first episode seed (default 0)")
    mw.add_argument("--max-attempts", type=int, default=None,
                    help="episodes to try at most (default 4n)")
    mw.add_argument("--post-success-steps", type=int, default=POST_SUCCESS_STEPS,
                    help=f"steps recorded after the first success (default {POST_SUCCESS_STEPS})")
    mw.add_argument("--max-episode-steps", type=int, default=None,
                    help="horizon (default 200, spec 8.3)")
    rec = sub.add_parser("record", help="successful episodes of your own policy")
    rec.add_argument("--suite", required=True, help="the run config's env.suite")
    rec.add_argument("--env-id", required=True, help="the run config's env.env_id")
    rec.add_argument("--options", default="{}",
                     help="the env options as JSON (max_episode_steps, env_kwargs, imports, ...)")
    rec.add_argument("--policy", required=True, help="module:callable, observation -> action")
    rec.add_argument("-n", type=int, default=5, help="successful demos to keep (default 5)")
    rec.add_argument("--out", required=True, type=Path, help="demo file to write (.h5)")
    rec.add_argument("--seed", type=int, default=0, help="first episode seed (default 0)")
    rec.add_argument("--max-attempts", type=int, default=None,
                     help="episodes to try at most (default 4n)")
    rec.add_argument("--post-success-steps", type=int, default=POST_SUCCESS_STEPS,
                     help=f"steps recorded after the first success (default {POST_SUCCESS_STEPS})")
    ad = sub.add_parser("adroit-convert", help="convert Adroit human demos (D4RL or Minari)")
    ad.add_argument("--task", required=True, help="door, pen, relocate or an Adroit env id")
    ad.add_argument("--in", dest="src", required=True, type=Path, help="D4RL or Minari HDF5 file")
    ad.add_argument("--out", required=True, type=Path, help="demo file to write (.h5)")
    ad.add_argument("--format", default="auto", choices=["auto", "d4rl", "minari"])
    ad.add_argument("--episodes", type=int, default=None, help="convert only the first N")
    args = parser.parse_args(argv)
    import warnings

    # gymnasium's env checker and MetaWorld's policies warn about things rfcl handles itself.
    warnings.filterwarnings("ignore", category=UserWarning)
    start = time.perf_counter()
    try:
        if args.command == "record":
            import json

            print(f"rfcl_sim.demos: {args.n} demos of {args.policy} in {args.env_id} -> {args.out}")
            options = json.loads(args.options)
            trajs = record(args.suite, args.env_id, options, args.policy, args.n, args.out,
                           args.seed, args.max_attempts, args.post_success_steps)
        elif args.command == "metaworld":
            print(f"rfcl_sim.demos: {args.n} scripted demos of {args.task} -> {args.out}")
            trajs = generate_metaworld(args.task, args.n, args.out, args.seed, args.max_attempts,
                                       args.post_success_steps, args.max_episode_steps)
        else:
            print(f"rfcl_sim.demos: Adroit {args.task} demos {args.src} -> {args.out}")
            trajs = convert_adroit(args.task, args.src, args.out, args.format, args.episodes)
    except (DemoSourceError, AdapterError, demo_file.DemoFileError) as e:
        print(f"rfcl_sim.demos: error: {e}", file=sys.stderr)
        return 1
    ok = sum(t.succeeded for t in trajs)
    print(f"wrote {len(trajs)} episodes ({ok} successful) to {args.out} and "
          f"{demo_file.sidecar_path(args.out)} in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
