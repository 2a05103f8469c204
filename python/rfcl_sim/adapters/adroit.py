"""Adroit (gymnasium-robotics 1.4.2) behind the adapter contract (spec 7.4, 8.3).

Tasks: ``AdroitHandDoorSparse-v1``, ``AdroitHandPenSparse-v1``, ``AdroitHandRelocateSparse-v1``
(the dense ids are accepted too: they differ only in the env's reward, which rfcl does not use).
The adapter drives the unwrapped env: rfcl owns time limits (H = 200, Pen 100, spec 8.3) and the
sparse reward (+1 per success step, from ``info["success"]``).

**State vector** (kind ``field`` entries, in this order): the fields of each env's own
``set_env_state`` dict, which is also the ``options["initial_state_dict"]`` its ``reset`` accepts:

==========  ===========================================================================================
Door        ``qpos`` (30), ``qvel`` (30), ``door_body_pos`` (3: the door frame's model position,
            randomised per episode)
Pen         ``qpos`` (30), ``qvel`` (30), ``desired_orien`` (4: the target pen's body quaternion,
            randomised per episode)
Relocate    ``qpos`` (36), ``qvel`` (36), ``obj_pos`` (3: the ball body's model position, the frame
            its six joints move in), ``target_pos`` (3: the target site's position)
==========  ===========================================================================================

Relocate's ``get_env_state`` reports the ball's *world* position under ``obj_pos`` while its
``set_env_state`` writes that value as the body's *model* position, so restoring the env's own
dict moves the ball by its joint offsets (the "contact bug" the reference works around, spec 7.4).
Our state stores the model position, which is what ``set_env_state`` writes, so a state restores
exactly; :func:`relocate_model_pos` converts a world position (D4RL files, the env's own dicts).

Resets: ``reset(seed, {})`` seeds the env (door position, pen goal or ball and target placement
come from the seed); ``reset(seed, {"initial_state_dict": {...}})`` then sets that state, as
gymnasium-robotics' own reset does (spec 7.4: how the human demos' initial states are given). The
dict holds the state fields above as lists of numbers.

**Rendering** (``render_size``, for eval videos): the env is made with ``render_mode="rgb_array"``
and ``width = height = render_size`` and renders through gymnasium's offscreen MuJoCo renderer
(``MUJOCO_GL``: set to ``egl`` when unset, see :func:`~rfcl_sim.adapters.fields.headless_gl`), from
the task's default camera unless ``env_kwargs`` gives ``camera_id``, ``camera_name`` or
``default_camera_config``.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import AdapterError, MakeOptions
from .fields import (FieldAdapter, check_env_kwargs, check_horizon, render_env_kwargs,
                     start_rendering)

#: env id -> (task short name, horizon H of spec 8.3, task fields after qpos and qvel).
TASKS: dict[str, tuple[str, int, tuple[tuple[str, int], ...]]] = {
    "AdroitHandDoorSparse-v1": ("door", 200, (("door_body_pos", 3),)),
    "AdroitHandPenSparse-v1": ("pen", 100, (("desired_orien", 4),)),
    "AdroitHandRelocateSparse-v1": ("relocate", 200, (("obj_pos", 3), ("target_pos", 3))),
}
#: The dense variants: the same simulation with another reward, which rfcl ignores.
DENSE_IDS = {sparse.replace("Sparse", ""): sparse for sparse in TASKS}
#: short task name ("door") -> sparse env id.
ENV_IDS = {name: env_id for env_id, (name, _, _) in TASKS.items()}
#: Constructor arguments of the Adroit envs that do not change the task.
ENV_KWARGS = ("render_mode", "width", "height", "camera_id", "camera_name",
              "default_camera_config")


def canonical_id(env_id: str) -> str:
    """The sparse env id for ``env_id``: a sparse id, its dense twin, or a short name ("door")."""
    if env_id in TASKS:
        return env_id
    if env_id in DENSE_IDS:
        return DENSE_IDS[env_id]
    if env_id in ENV_IDS:
        return ENV_IDS[env_id]
    raise AdapterError(
        f"adroit: unknown env '{env_id}'; expected one of {sorted(TASKS)} (or their dense ids, "
        f"or {sorted(ENV_IDS)})"
    )


def make(env_id: str, **kwargs: Any) -> "AdroitAdapter":
    """An Adroit adapter for ``env_id`` (see :func:`canonical_id`); default horizon 200, Pen
    100 (spec 8.3). Keyword arguments: those of :class:`~rfcl_sim.adapters.base.MakeOptions`.
    """
    return AdroitAdapter(env_id, MakeOptions.of("adroit", env_id, kwargs))


class AdroitAdapter(FieldAdapter):
    """One Adroit hand task (see the module docs for the state and resets)."""

    suite = "adroit"

    def __init__(self, env_id: str, make_options: MakeOptions = MakeOptions()) -> None:
        # First: with render_size it sets MUJOCO_GL, which MuJoCo reads when it is imported.
        self.render_size = start_rendering("adroit", make_options.render_size)
        import gymnasium as gym
        import gymnasium_robotics

        self.env_id = canonical_id(env_id)
        self.task, default_horizon, task_fields = TASKS[self.env_id]
        if make_options.control_mode not in (None, "default"):
            raise AdapterError(
                f"adroit: control_mode '{make_options.control_mode}' is not available for "
                f"{self.env_id}; Adroit has one controller (joint position targets): use null"
            )
        env_kwargs = check_env_kwargs("adroit", self.env_id, make_options.env_kwargs, ENV_KWARGS)
        env_kwargs = render_env_kwargs("adroit", self.env_id, env_kwargs, self.render_size)
        self.horizon = check_horizon("adroit", make_options.max_episode_steps, default_horizon)
        gym.register_envs(gymnasium_robotics)
        self._wrapped = gym.make(self.env_id, **env_kwargs)
        self._env = self._wrapped.unwrapped
        self._rng = np.random.default_rng(make_options.seed)
        model = self._env.model
        self._layout = [("qpos", "field", int(model.nq)), ("qvel", "field", int(model.nv))]
        self._layout += [(name, "field", n) for name, n in task_fields]
        self.obs_dim = int(self._wrapped.observation_space.shape[0])
        self.action_dim = int(self._wrapped.action_space.shape[0])
        self.reset(int(self._rng.integers(2**31)), {})

    # The contract -------------------------------------------------------------------------------

    def reset(self, seed: int | None, options: dict[str, Any]) -> np.ndarray:
        options = dict(options or {})
        initial = options.pop("initial_state_dict", None)
        if options:
            raise AdapterError(
                f"adroit: reset options {sorted(options)} are not understood by {self.env_id}; "
                "expected none or 'initial_state_dict'"
            )
        obs, _ = self._env.reset(seed=self._reset_seed(seed))
        if initial is not None:
            return self.set_state(self.state_from_dict(initial, "reset options.initial_state_dict"))
        return np.asarray(obs, dtype=np.float32)

    def set_state(self, state: np.ndarray) -> np.ndarray:
        parts = self._state_fields(state)
        env = self._env
        if self.task == "door":
            env.model.body_pos[env.door_body_id] = parts["door_body_pos"]
        elif self.task == "pen":
            env.model.body_quat[env.target_obj_body_id] = parts["desired_orien"]
        else:
            env.model.body_pos[env.obj_body_id] = parts["obj_pos"]
            env.model.site_pos[env.target_obj_site_id] = parts["target_pos"]
        # Cleared so that stepping from a restored state does not depend on the env's history.
        env.data.qacc_warmstart[:] = 0.0
        env.set_state(parts["qpos"].astype(np.float64), parts["qvel"].astype(np.float64))
        return np.asarray(env._get_obs(), dtype=np.float32)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, bool]:
        a = self._check_action(action)
        obs, _, _, _, info = self._env.step(np.clip(a, -1.0, 1.0))
        return np.asarray(obs, dtype=np.float32), bool(info["success"])

    def get_state(self) -> np.ndarray:
        env = self._env
        if self.task == "door":
            extra = [env.model.body_pos[env.door_body_id]]
        elif self.task == "pen":
            extra = [env.model.body_quat[env.target_obj_body_id]]
        else:
            extra = [env.model.body_pos[env.obj_body_id],
                     env.model.site_pos[env.target_obj_site_id]]
        return np.concatenate([env.data.qpos, env.data.qvel, *extra]).astype(np.float32)

    # Beyond the contract -------------------------------------------------------------------------

    def state_from_dict(self, fields: dict[str, Any], where: str) -> np.ndarray:
        """The flat state of a dict with this task's state fields (module docs); ``where`` names
        the dict's origin in errors. Extra keys of the env's own ``get_env_state`` dicts
        (``hand_qpos``, ``palm_pos``) are ignored."""
        if not isinstance(fields, dict):
            raise AdapterError(f"adroit: {where} must be a dict of state fields, got "
                               f"{type(fields).__name__}")
        values = []
        for name, _, n in self._layout:
            if name not in fields:
                raise AdapterError(
                    f"adroit: {where} lacks '{name}'; {self.env_id} needs "
                    f"{[f for f, _, _ in self._layout]}"
                )
            v = np.asarray(fields[name], dtype=np.float64).reshape(-1)
            if v.size != n:
                raise AdapterError(
                    f"adroit: {where}['{name}'] has {v.size} values, {self.env_id} expects {n}"
                )
            values.append(v)
        return np.concatenate(values).astype(np.float32)

    def state_to_dict(self, state: np.ndarray) -> dict[str, list[float]]:
        """The inverse of :meth:`state_from_dict`, with JSON-ready lists."""
        return {k: [float(x) for x in v] for k, v in self._split(self._check_state(state)).items()}

    def relocate_model_pos(self, qpos: np.ndarray, obj_world: np.ndarray,
                           target_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Relocate only: the ball body's model position and the target site's position that put
        the ball at world position ``obj_world`` with joint positions ``qpos`` and the target at
        ``target_world``. The ball's world position is its model position moved by its joints,
        so the gap is measured once with the current model position and removed."""
        if self.task != "relocate":
            raise AdapterError(f"adroit: relocate_model_pos is for Relocate, not {self.env_id}")
        import mujoco

        env = self._env
        env.data.qpos[:] = np.asarray(qpos, dtype=np.float64)
        env.data.qvel[:] = 0.0
        mujoco.mj_forward(env.model, env.data)
        gap = env.data.xpos[env.obj_body_id] - env.model.body_pos[env.obj_body_id]
        target_gap = (env.data.site_xpos[env.target_obj_site_id]
                      - env.model.site_pos[env.target_obj_site_id])
        return (np.asarray(obj_world, dtype=np.float64) - gap,
                np.asarray(target_world, dtype=np.float64) - target_gap)

    def palm_pos(self, qpos: np.ndarray) -> np.ndarray:
        """The palm site's world position for hand joint positions ``qpos`` (Relocate's
        observations are relative to it)."""
        import mujoco

        env = self._env
        env.data.qpos[:] = np.asarray(qpos, dtype=np.float64)
        mujoco.mj_forward(env.model, env.data)
        return env.data.site_xpos[env.S_grasp_site_id].copy()
