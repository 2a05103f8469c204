"""ManiSkill3 (3.0.1) adapter: one CPU-simulated env, state observations (spec 7.1).

The env is ``gym.make(env_id, obs_mode="state", control_mode=..., sim_backend="physx_cpu",
num_envs=1, reward_mode="sparse", render_mode=None, **env_kwargs)``, driven through its unwrapped
``BaseEnv`` so that no gymnasium wrapper ends, truncates or re-checks episodes: the Rust actor owns
rewards and time limits.

**State vector.** ``get_state_dict()`` returns ``{"actors": {name: [1, 13]}, "articulations":
{name: [1, 13 + 2 dof]}}``. It is flattened actors first, then articulations, each group in the
dict's own order, which is the order in which the task registered its entities (``table-workspace``,
``cube``, ``goal_site``, then ``panda`` for PickCube-v1). That is the order ManiSkill's
``RecordEpisode`` and ``replay_trajectory`` write the ``env_states`` groups in (they create them with
``track_order=True``) and in which core/src/demo reads them back (link creation order), so a demo
state from a file and a state from this adapter are the same vector. An actor is pos 3, quat 4
(wxyz), linear velocity 3, angular velocity 3; an articulation is root pose 7, root velocity 6,
qpos dof, qvel dof (core/src/demo/layout.rs). The layout is read once, after the first reset, and
checked on every ``get_state``: a task whose entities change between resets is reported, not
silently mis-flattened.

**Seeds.** ManiSkill seeds NumPy RNGs, which take seeds below 2**32. Seeds below 2**31 (demo seeds,
forward-curriculum levels) pass unchanged; larger ones (rfcl's held-out eval seeds start at 2**40)
are hashed into [2**31, 2**32), so they never collide with the small ones.

**Actions** in ``[-1, 1]`` are mapped affinely onto the env's action box (the identity for the
normalised ``pd_joint_delta_pos`` controller).

**Rendering** (``render_size``, for eval videos): the env is made with ``render_mode="rgb_array"``
and ``human_render_camera_configs`` setting the task's human render cameras to ``render_size`` x
``render_size``; ``render()`` is ``render_rgb_array`` of the task's ``render_camera`` (else its
first human render camera), which shows the goal markers the observations do not. SAPIEN renders
through Vulkan: on a GPU, or on the CPU with Mesa's lavapipe (``render_backend`` stays ManiSkill's
default, which falls back to the CPU without CUDA; ``env_kwargs`` may set it). Those cameras exist
whether or not the adapter renders and carry no physics, so ``render_size`` changes neither the state
nor the dynamics. Without ``render_size`` the env is made exactly as before.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import Adapter, AdapterError, MakeOptions, check_render_size, import_modules

SUITE = "maniskill3"
DEFAULT_CONTROL_MODE = "pd_joint_delta_pos"
DEFAULT_SIM_BACKEND = "physx_cpu"

#: The keyword arguments :func:`make` understands (the run config's env section, spec 7.1): the
#: common ones (:class:`MakeOptions`) and :data:`OWN_KWARGS`, in the order its errors list them.
KWARGS = (
    "control_mode", "max_episode_steps", "env_kwargs", "seed", "sim_backend", "render_size", "imports",
)
#: The options of :data:`KWARGS` beyond the common ones, keyword arguments of the adapter itself.
OWN_KWARGS = ("sim_backend", "imports")


def fold_seed(seed: int) -> int:
    """A 64-bit rfcl seed as a ManiSkill seed (below 2**32): see the module docs."""
    if seed < 0:
        raise AdapterError(f"seed {seed} is negative; seeds are unsigned")
    if seed < 2**31:
        return seed
    z = (seed + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    z ^= z >> 31
    return 2**31 + (z % 2**31)


def make(env_id: str, **kwargs: Any) -> "ManiSkillAdapter":
    unknown = sorted(set(kwargs) - set(KWARGS))
    if unknown:
        raise AdapterError(
            f"maniskill3 adapter: unknown option(s) {unknown}; expected some of {list(KWARGS)}"
        )
    own = {k: kwargs.pop(k) for k in OWN_KWARGS if k in kwargs}
    return ManiSkillAdapter(env_id, MakeOptions(**kwargs), **own)


class ManiSkillAdapter(Adapter):
    suite = SUITE

    def __init__(self, env_id: str, make_options: MakeOptions = MakeOptions(),
                 sim_backend: str | None = None, imports: list[str] | None = None) -> None:
        self.render_size = check_render_size(SUITE, make_options.render_size)
        import gymnasium as gym
        import mani_skill.envs  # noqa: F401  (registers the tasks)
        from mani_skill.utils.registration import REGISTERED_ENVS

        # Modules of the config's env.imports register the user's own tasks.
        import_modules(SUITE, imports)
        if env_id not in REGISTERED_ENVS:
            raise AdapterError(
                f"ManiSkill3 has no env '{env_id}' (e.g. PickCube-v1, StackCube-v1, "
                "PegInsertionSide-v1, PlugCharger-v1; an env of your own package is registered "
                "when the config lists its module in env.imports)"
            )
        extra = dict(make_options.env_kwargs or {})
        fixed = {"obs_mode", "sim_backend", "num_envs", "reward_mode", "control_mode", "render_mode"}
        clash = sorted(fixed & set(extra))
        if clash:
            raise AdapterError(
                f"env_kwargs must not set {clash}: the adapter fixes obs_mode=state, num_envs=1, "
                "reward_mode=sparse; control_mode, sim_backend and render_size (which sets "
                "render_mode) are options of their own"
            )
        render: dict[str, Any] = {"render_mode": None}
        if self.render_size is not None:
            cameras = dict(extra.pop("human_render_camera_configs", None) or {})
            sized = sorted({"width", "height"} & set(cameras))
            if sized:
                raise AdapterError(
                    f"env_kwargs.human_render_camera_configs must not set {sized} with "
                    "render_size, which sets the render cameras' width and height"
                )
            cameras.update(width=self.render_size, height=self.render_size)
            render = {"render_mode": "rgb_array", "human_render_camera_configs": cameras}
        self.env_id = env_id
        self.control_mode = make_options.control_mode or DEFAULT_CONTROL_MODE
        self.sim_backend = sim_backend or DEFAULT_SIM_BACKEND
        horizon = make_options.max_episode_steps or REGISTERED_ENVS[env_id].max_episode_steps
        self.horizon = int(horizon or 0)
        if self.horizon <= 0:
            raise AdapterError(f"{env_id} has no registered horizon: set max_episode_steps")
        self._gym_env = gym.make(
            env_id,
            obs_mode="state",
            control_mode=self.control_mode,
            sim_backend=self.sim_backend,
            num_envs=1,
            reward_mode="sparse",
            **render,
            **extra,
        )
        self._env = self._gym_env.unwrapped
        space = self._env.single_action_space
        self.action_dim = int(np.prod(space.shape))
        self._low = np.asarray(space.low, dtype=np.float32).reshape(-1)
        self._high = np.asarray(space.high, dtype=np.float32).reshape(-1)
        self._identity_actions = bool(np.all(self._low == -1.0) and np.all(self._high == 1.0))
        # The first reset builds the scene (and seeds the env's RNG chain for unseeded resets).
        obs = self.reset(make_options.seed, {})
        self.obs_dim = int(obs.shape[0])
        self._layout = self._layout_of(self._env.get_state_dict())
        self._render_camera: str | None = None
        if self.render_size is not None:
            if not self._env.scene.can_render():
                self._gym_env.close()
                raise RuntimeError(
                    f"maniskill3: render_size was given but SAPIEN cannot render on "
                    f"{self._env.backend.render_device} (render_backend "
                    f"{self._env.backend.render_backend!r}); on a machine without a GPU it renders "
                    "through Vulkan with Mesa's lavapipe (Debian: mesa-vulkan-drivers >= 24.3 from "
                    "bookworm-backports, libvulkan1)"
                )
            cameras = list(self._env.scene.human_render_cameras)
            if not cameras:
                self._gym_env.close()
                raise AdapterError(f"{env_id} has no human render camera: it cannot render")
            self._render_camera = "render_camera" if "render_camera" in cameras else cameras[0]

    # The contract -------------------------------------------------------------------------------

    def state_layout(self) -> list[tuple[str, str, int]]:
        return list(self._layout)

    def reset(self, seed: int | None, options: dict[str, Any]) -> np.ndarray:
        opts = dict(options or {})
        obs, _info = self._env.reset(
            seed=None if seed is None else fold_seed(int(seed)), options=opts
        )
        return self._row(obs)

    def set_state(self, state: np.ndarray) -> np.ndarray:
        import torch

        s = self._check_state(state)
        state_dict: dict[str, dict[str, Any]] = {"actors": {}, "articulations": {}}
        offset = 0
        for name, _kind, n in self._layout:
            group, entity = name.split("/", 1)
            state_dict[group][entity] = torch.from_numpy(s[offset : offset + n].copy()).reshape(1, n)
            offset += n
        self._env.set_state_dict(state_dict)
        return self._row(self._env.get_obs())

    def step(self, action: np.ndarray) -> tuple[np.ndarray, bool]:
        a = self._check_action(action)
        if not self._identity_actions:
            a = self._low + (np.clip(a, -1.0, 1.0) + 1.0) * 0.5 * (self._high - self._low)
        obs, _reward, _terminated, _truncated, info = self._env.step(a)
        if "success" not in info:
            raise AdapterError(f"{self.env_id} reports no 'success' in its step info")
        return self._row(obs), bool(np.asarray(_numpy(info["success"])).reshape(-1)[0])

    def get_state(self) -> np.ndarray:
        state_dict = self._env.get_state_dict()
        parts = []
        for group, entities in _groups(state_dict):
            for entity, value in entities.items():
                parts.append((f"{group}/{entity}", _numpy(value).reshape(-1)))
        names = [(name, len(v)) for name, v in parts]
        expected = [(name, n) for name, _, n in self._layout]
        if names != expected:
            raise AdapterError(
                f"{self.env_id}: the state dict now holds {names}, but the layout read at the first "
                f"reset is {expected}"
            )
        return np.concatenate([v for _, v in parts]).astype(np.float32, copy=False)

    def render(self) -> np.ndarray:
        if self.render_size is None:
            raise self._no_render_size()
        return self._frame(self._env.render_rgb_array(camera_name=self._render_camera))

    def close(self) -> None:
        self._gym_env.close()

    # Helpers ------------------------------------------------------------------------------------

    def _layout_of(self, state_dict: dict[str, Any]) -> list[tuple[str, str, int]]:
        layout = []
        for group, entities in _groups(state_dict):
            kind = "actor" if group == "actors" else "articulation"
            for entity, value in entities.items():
                layout.append((f"{group}/{entity}", kind, int(_numpy(value).reshape(-1).shape[0])))
        return layout

    def _row(self, obs: Any) -> np.ndarray:
        o = _numpy(obs)
        if o.ndim != 2 or o.shape[0] != 1:
            raise AdapterError(
                f"{self.env_id}: expected a [1, D] state observation, got shape {o.shape}"
            )
        return o[0].astype(np.float32, copy=False)


def _groups(state_dict: dict[str, Any]):
    """``actors`` then ``articulations``, each in its dict order; anything else is an error."""
    other = sorted(set(state_dict) - {"actors", "articulations"})
    if other:
        raise AdapterError(
            f"the ManiSkill state dict has groups {other} beyond actors and articulations; this "
            "adapter cannot flatten them"
        )
    for group in ("actors", "articulations"):
        yield group, state_dict.get(group, {})


def _numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        return x.detach().cpu().numpy()
    return np.asarray(x)
