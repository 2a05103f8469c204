"""MetaWorld 3.1.1 behind the adapter contract (spec 7.3, 8.3).

The env is built with ``gym.make("Meta-World/MT1", env_name=<task>)``, MetaWorld's own entry point,
which sets the task goal-observable (``partially_observable=False``): the last 3 of the 39
observation values are the goal position, as in the reference's ``<task>-v2-goal-observable``
envs. The adapter then drives the unwrapped Sawyer env directly, because rfcl owns everything
MT1's wrappers add: time limits, termination on success, episode statistics and task sampling.

**Task distribution.** MT1 samples each episode from 50 goals fixed at construction (from its
``seed``, which the adapter sets to 0 as those goals are never used). The
reference instead draws a fresh random vector per episode from the task's whole reset space,
seeded per episode (spec 7.3: "seeded_rand_vec on, rand vector not frozen"), so that a level of
the forward curriculum (one seed) is one object/goal placement. We do the same: ``reset(seed)``
seeds the env's RNG, draws the task's random vector (object and goal placement) from it, rebuilds
the scene from it and freezes it; then, like the reference, takes **one zero-action step**, whose
observation is the initial observation (it fills the previous-frame block with a real frame).

**State vector** (kind ``field`` entries, in this order):

=============  =====================================================================================
``qpos``       MuJoCo ``data.qpos`` (``nq`` values: arm, gripper, objects' free/slide joints)
``qvel``       MuJoCo ``data.qvel`` (``nv`` values)
``mocap_pos``  the end-effector mocap target position (3); actions move it, so it is state
``mocap_quat`` the mocap target orientation (4)
``rand_vec``   the task's random vector ``_last_rand_vec`` (object and goal placement; its length
               depends on the task, e.g. 6 for pick-place-v3: object xyz, goal xyz)
``prev_frame`` the 18 previous-frame values of the observation (MetaWorld stacks two frames), so
               that the observation returned by :meth:`set_state` is exactly the recorded one
=============  =====================================================================================

Restoring follows spec 7.3: unless the preceding reset drew exactly the state's ``rand_vec``
(bit for bit: a seeded reset's float64 vector differs from the state's float32 copy, so a restore
usually rebuilds, about 5 ms), the scene (object placement, goal site, the task's reward
bookkeeping) is rebuilt from it with the vector frozen; then mocap, qpos and qvel are written and
MuJoCo's warm start is cleared. So a restored state steps the same whatever the env did before.

Success is ``info["success"]`` of every step; the env never terminates (rfcl owns time limits).

**Rendering** (``render_size``, for eval videos): the Sawyer env is made with
``render_mode="rgb_array"`` and ``width = height = render_size`` and renders through gymnasium's
offscreen MuJoCo renderer (``MUJOCO_GL``: set to ``egl`` when unset, see
:func:`~rfcl_sim.adapters.fields.headless_gl`). The camera is :data:`RENDER_CAMERA` unless
``env_kwargs`` names one (``camera_name`` or ``camera_id``). MetaWorld's fixed ``corner*`` cameras
are defined upside down (for mujoco-py, which read frames bottom row first), so their frames are
turned by 180 degrees: what ``render()`` returns is upright.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import AdapterError, MakeOptions
from .fields import (FieldAdapter, check_env_kwargs, check_horizon, render_env_kwargs,
                     start_rendering)

#: Spec 8.3: MetaWorld tasks run for H = 200 steps (train and eval).
DEFAULT_HORIZON = 200
#: The constructor arguments of the unwrapped Sawyer env that MT1 passes through; the other MT1
#: options configure wrappers this adapter does not use (one-hot task ids, reward normalisation).
ENV_KWARGS = ("reward_function_version", "render_mode", "camera_name", "camera_id", "width",
              "height")
#: MetaWorld's one controller: end-effector mocap deltas plus a gripper effort.
CONTROL_MODES = (None, "default")
#: Observation layout: hand xyz, gripper opening, 14 object values = one 18-value frame.
FRAME_LEN = 18
#: The step count MetaWorld refuses to step past; rfcl truncates episodes itself.
_NO_PATH_LIMIT = 2**62
#: The camera of ``render()`` when ``env_kwargs`` names none: the table seen from its front corner.
RENDER_CAMERA = "corner"
#: MetaWorld's cameras whose up vector points down (xyz_base.xml): frames turned by 180 degrees.
UPSIDE_DOWN_CAMERAS = ("corner", "corner2", "corner3", "corner4")


def task_names() -> list[str]:
    """Every MetaWorld v3 task this adapter can make (MetaWorld's own list)."""
    import metaworld

    return sorted(metaworld.ALL_V3_ENVIRONMENTS)


def make(env_id: str, **kwargs: Any) -> "MetaWorldAdapter":
    """A MetaWorld adapter for task ``env_id`` (e.g. ``"pick-place-v3"``); default horizon 200
    (spec 8.3). Keyword arguments: those of :class:`~rfcl_sim.adapters.base.MakeOptions`.
    """
    return MetaWorldAdapter(env_id, MakeOptions.of("metaworld", env_id, kwargs))


class MetaWorldAdapter(FieldAdapter):
    """One goal-observable MetaWorld task (see the module docs for resets and the state)."""

    suite = "metaworld"

    def __init__(self, env_id: str, make_options: MakeOptions = MakeOptions()) -> None:
        # First: with render_size it sets MUJOCO_GL, which MuJoCo reads when it is imported.
        self.render_size = start_rendering("metaworld", make_options.render_size)
        import gymnasium as gym
        import metaworld  # noqa: F401  (registers the Meta-World/* env ids)

        if env_id not in metaworld.ALL_V3_ENVIRONMENTS:
            raise AdapterError(
                f"metaworld: unknown task '{env_id}'; expected a MetaWorld v3 task name such as "
                f"'pick-place-v3' (all: {', '.join(task_names())})"
            )
        if make_options.control_mode not in CONTROL_MODES:
            raise AdapterError(
                f"metaworld: control_mode '{make_options.control_mode}' is not available for "
                f"{env_id}; MetaWorld has one controller (end-effector deltas + gripper): use null"
            )
        env_kwargs = check_env_kwargs("metaworld", env_id, make_options.env_kwargs, ENV_KWARGS)
        env_kwargs = render_env_kwargs("metaworld", env_id, env_kwargs, self.render_size)
        if self.render_size is not None and not {"camera_name", "camera_id"} & set(env_kwargs):
            env_kwargs["camera_name"] = RENDER_CAMERA
        self.env_id = env_id
        self.horizon = check_horizon("metaworld", make_options.max_episode_steps, DEFAULT_HORIZON)
        # MT1's seed only fixes its 50 goals, which resets replace (module docs); a constant keeps
        # construction deterministic and within the 32-bit seeds MT1 takes.
        self._wrapped = gym.make("Meta-World/MT1", env_name=env_id, seed=0, **env_kwargs)
        env = self._wrapped.unwrapped
        # MT1's tasks carry partially_observable=False (the goal is observed); set one so the env
        # takes it, then sample our own random vectors (module docs).
        env.set_task(env_task(self._wrapped))
        env.max_path_length = _NO_PATH_LIMIT
        self._env = env
        if self.render_size is not None:
            import mujoco

            camera = mujoco.mj_id2name(env.model, mujoco.mjtObj.mjOBJ_CAMERA,
                                       env.mujoco_renderer.camera_id)
            self._rotate_frames = camera in UPSIDE_DOWN_CAMERAS
        self._rng = np.random.default_rng(make_options.seed)
        self.obs_dim = int(env.sawyer_observation_space.shape[0])
        self.action_dim = int(env.action_space.shape[0])
        self._obs_low = env.sawyer_observation_space.low
        self._obs_high = env.sawyer_observation_space.high
        # Reset once so that the random vector (and so the state layout) exists.
        self.reset(int(self._rng.integers(2**31)), {})
        self._layout = [
            ("qpos", "field", int(env.model.nq)),
            ("qvel", "field", int(env.model.nv)),
            ("mocap_pos", "field", 3),
            ("mocap_quat", "field", 4),
            ("rand_vec", "field", int(np.asarray(env._last_rand_vec).size)),
            ("prev_frame", "field", FRAME_LEN),
        ]

    # The contract -------------------------------------------------------------------------------

    def reset(self, seed: int | None, options: dict[str, Any]) -> np.ndarray:
        if options:
            raise AdapterError(
                f"metaworld: reset options {sorted(options)} are not understood by {self.env_id}; "
                "MetaWorld resets take a seed only (options must be empty)"
            )
        env = self._env
        env.seed(self._reset_seed(seed))
        env._freeze_rand_vec = False
        env.seeded_rand_vec = True
        env.reset()
        env._freeze_rand_vec = True
        # Spec 7.3: the initial observation is the one after a zero-action step.
        obs, _ = self._step_env(np.zeros(self.action_dim, dtype=np.float32))
        return obs

    def set_state(self, state: np.ndarray) -> np.ndarray:
        import mujoco

        parts = self._state_fields(state)
        env = self._env
        rand_vec = parts["rand_vec"].astype(np.float64)
        if not np.array_equal(np.asarray(env._last_rand_vec, dtype=np.float64), rand_vec):
            # Spec 7.3: rebuild object and goal placement from the state's random vector. Also
            # when it differs from the reset's only by float32 rounding, so that the scene (goal
            # site, the task's reward bookkeeping) is exactly the same whatever came before.
            env._last_rand_vec = rand_vec
            env._freeze_rand_vec = True
            # The second half of env.reset() (MuJocoEnv.reset: clear the data, reset_model), which
            # is all that shapes the scene; the first half's reset_model is wiped by it.
            mujoco.mj_resetData(env.model, env.data)
            env.reset_model()
        env.data.mocap_pos[0] = parts["mocap_pos"]
        env.data.mocap_quat[0] = parts["mocap_quat"]
        env.data.qacc_warmstart[:] = 0.0
        env.set_state(parts["qpos"].astype(np.float64), parts["qvel"].astype(np.float64))
        env._did_see_sim_exception = False
        env.curr_path_length = 0
        env._prev_obs = parts["prev_frame"].astype(np.float64)
        obs = np.clip(env._get_obs(), self._obs_low, self._obs_high)
        self._obs = obs.astype(np.float32)
        return self._obs.copy()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, bool]:
        a = self._check_action(action)
        return self._step_env(np.clip(a, -1.0, 1.0))

    def get_state(self) -> np.ndarray:
        env = self._env
        return np.concatenate([
            env.data.qpos,
            env.data.qvel,
            env.data.mocap_pos[0],
            env.data.mocap_quat[0],
            np.asarray(env._last_rand_vec).reshape(-1),
            # The previous frame of the last observation (the env itself only keeps the current).
            self._obs[FRAME_LEN:2 * FRAME_LEN],
        ]).astype(np.float32)

    # Helpers -------------------------------------------------------------------------------------

    def _step_env(self, action: np.ndarray) -> tuple[np.ndarray, bool]:
        obs, _, _, _, info = self._env.step(action)
        self._obs = np.asarray(obs, dtype=np.float32)
        return self._obs.copy(), bool(info["success"])


def env_task(wrapped: Any) -> Any:
    """The first of MT1's tasks (all carry the same observability flag; the goal they fix is
    replaced at every reset)."""
    env = wrapped
    while not hasattr(env, "tasks"):
        if not hasattr(env, "env"):
            raise AdapterError("metaworld: Meta-World/MT1 returned an env without its task list")
        env = env.env
    return env.tasks[0]
