"""Your own task: any Gymnasium env that can save and restore its state (``env.suite: gymnasium``).

The env is ``gymnasium.make(env_id, **env_kwargs)`` after importing the modules the config lists
in ``env.imports`` (where your package registers its envs), or, for an ``env_id`` of the form
``module:callable``, whatever that callable returns when called with ``**env_kwargs``. Nothing in
rfcl changes when you add a task (docs/YOUR_TASK.md is the tutorial).

**State** (what a reverse curriculum restores, spec 2.4), found in this order:

1. **The rfcl protocol**, methods of your env (or of any wrapper around it):

   * ``rfcl_get_state() -> np.ndarray``: the state as a flat float vector;
   * ``rfcl_set_state(state)``: restores it (rfcl calls it right after ``reset(seed=...,
     options=...)`` with the demo's seed and options, so what the seed decides, such as a goal or
     the objects' shapes, need not be in the vector); it may return the observation of the
     restored state, else the adapter calls ``rfcl_get_obs()``;
   * optionally ``rfcl_state_layout() -> [(name, length), ...]``: named parts of the vector (one
     part ``state`` otherwise). Names ending in ``vel`` are velocities, names ending in ``quat``
     (4 values) orientations, everything else positions: that is how ``rfcl demos inspect
     --replay`` judges a replay (docs/SUITES.md, "Checking demos").

2. **MuJoCo, with no code of yours**: an env whose unwrapped env has MuJoCo ``model`` and ``data``
   (Gymnasium's ``MujocoEnv`` and Gymnasium-Robotics' envs) gets the fields ``qpos``, ``qvel``,
   then ``mocap_pos`` and ``mocap_quat`` when the model has mocap bodies and ``act`` when it has
   activations; restoring writes them and runs ``mj_forward``. The observation of a restored
   state is the unwrapped env's ``_get_obs()`` (the convention of Gymnasium's MuJoCo envs; a
   goal-conditioned env's dict observation included).

Observation wrappers around the env are applied to a restored state's observation too, innermost
first (spec 2.4 step 6). Dict and tuple observations are flattened (``gymnasium.spaces.flatten``).

**Success** is ``info["success"]``, or ``info["is_success"]`` (Gymnasium-Robotics' name), of
every step; or, for an env that reports neither (Gymnasium's own MuJoCo envs), what the callable
the config names in ``env.success`` (``module:callable``) says when called with the unwrapped env,
the step's observation and its info. **Actions** must be a bounded ``Box``; rfcl's actions in ``[-1, 1]`` are mapped
affinely onto it. Episodes are never ended by the adapter: ``terminated`` and ``truncated`` are
ignored (rfcl owns time limits, spec 5.6); the horizon is ``max_episode_steps`` from the config,
else the env's registered one.

**Checks when the adapter is made**, each one line naming the env and what was expected: no state
functions; an action space that is not a bounded ``Box``; an observation that is not finite or
whose size changes; a restore that does not reproduce the state (set then get differs by more
than :data:`RESTORE_TOLERANCE`); a layout whose lengths do not add up to the state's.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import (Adapter, AdapterError, MakeOptions, check_render_size, entry_point,
                   import_modules)
from .fields import check_horizon, headless_gl, render_env_kwargs

SUITE = "gymnasium"
#: The options :func:`make` understands beyond the common ones (:class:`MakeOptions`).
OWN_KWARGS = ("imports", "success")
#: The options :func:`make` understands: those of the other suites, plus :data:`OWN_KWARGS`.
KWARGS = (*MakeOptions.names(), *OWN_KWARGS)
#: Largest difference between a state and the state read back after restoring it.
RESTORE_TOLERANCE = 1e-5


def make(env_id: str, **kwargs: Any) -> "GymnasiumAdapter":
    """A gymnasium adapter for ``env_id`` (module docs); keyword arguments: :data:`KWARGS`."""
    own = {k: kwargs.pop(k) for k in OWN_KWARGS if k in kwargs}
    return GymnasiumAdapter(env_id, MakeOptions.of(SUITE, env_id, kwargs), **own)


class GymnasiumAdapter(Adapter):
    suite = SUITE

    def __init__(self, env_id: str, make_options: MakeOptions = MakeOptions(),
                 imports: list[str] | None = None, success: str | None = None) -> None:
        import gymnasium as gym

        self.env_id = env_id
        if make_options.control_mode is not None:
            raise AdapterError(
                f"{SUITE}: control_mode is not an option of {env_id}: set the controller through "
                "env_kwargs, which go to the env's constructor"
            )
        import_modules(SUITE, imports)
        self._success = None if success is None else entry_point(SUITE, success)
        self.render_size = check_render_size(SUITE, make_options.render_size)
        kwargs = dict(make_options.env_kwargs or {})
        if self.render_size is not None:
            headless_gl()
            kwargs = render_env_kwargs(SUITE, env_id, kwargs, self.render_size)
        try:
            if ":" in env_id:
                env = entry_point(SUITE, env_id)(**kwargs)
            else:
                env = gym.make(env_id, **kwargs)
        except AdapterError:
            raise
        except gym.error.Error as e:
            raise AdapterError(
                f"{SUITE}: gymnasium cannot make '{env_id}' ({e}); list the module that registers "
                "it in env.imports, or give env_id as module:callable"
            ) from e
        if not isinstance(env, gym.Env):
            raise AdapterError(
                f"{SUITE}: {env_id} made a {type(env).__name__}, not a gymnasium.Env"
            )
        self._wrapped = env
        self._env = env.unwrapped
        spec = getattr(env, "spec", None)
        self.horizon = check_horizon(
            SUITE, make_options.max_episode_steps, getattr(spec, "max_episode_steps", None) or 0)
        if self.horizon <= 0:
            raise AdapterError(
                f"{SUITE}: {env_id} has no registered max_episode_steps: set env.max_episode_steps"
            )
        self._rng = np.random.default_rng(make_options.seed)
        self._low, self._high = self._action_bounds(env.action_space)
        self.action_dim = int(self._low.shape[0])
        self._obs_space = env.observation_space
        self._state = self._state_functions()
        obs = self.reset(int(self._rng.integers(2**31)), {})
        self.obs_dim = int(obs.shape[0])
        state = self._state.get()
        self._layout = self._state.layout(state)
        self._check_restore(state, obs)

    # The contract -------------------------------------------------------------------------------

    def state_layout(self) -> list[tuple[str, str, int]]:
        return list(self._layout)

    def reset(self, seed: int | None, options: dict[str, Any]) -> np.ndarray:
        if seed is None:
            seed = int(self._rng.integers(2**63))
        elif isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise AdapterError(f"{SUITE}: reset seed must be a non-negative integer, got {seed!r}")
        obs, _info = self._wrapped.reset(seed=int(seed), options=dict(options) or None)
        return self._flat_obs(obs, "reset")

    def set_state(self, state: np.ndarray) -> np.ndarray:
        s = self._check_state(state)
        if not np.all(np.isfinite(s)):
            raise AdapterError(f"{SUITE}: a state of {self.env_id} has a value that is not finite")
        return self._flat_obs(self._state.set(s), "set_state")

    def step(self, action: np.ndarray) -> tuple[np.ndarray, bool]:
        a = self._check_action(action)
        a = self._low + (np.clip(a, -1.0, 1.0) + 1.0) * 0.5 * (self._high - self._low)
        obs, _reward, _terminated, _truncated, info = self._wrapped.step(a)
        flat = self._flat_obs(obs, "step")
        if self._success is not None:
            return flat, bool(self._success(self._env, obs, info))
        return flat, success_of(self.env_id, info)

    def get_state(self) -> np.ndarray:
        return np.asarray(self._state.get(), dtype=np.float32).reshape(-1)

    def render(self) -> np.ndarray:
        if self.render_size is None:
            raise self._no_render_size()
        return self._frame(self._wrapped.render())

    def close(self) -> None:
        self._wrapped.close()

    # Checks and helpers --------------------------------------------------------------------------

    def _action_bounds(self, space: Any) -> tuple[np.ndarray, np.ndarray]:
        from gymnasium import spaces

        if not isinstance(space, spaces.Box):
            raise AdapterError(
                f"{SUITE}: the action space of {self.env_id} is {space}; rfcl needs a bounded Box"
            )
        low = np.asarray(space.low, dtype=np.float32).reshape(-1)
        high = np.asarray(space.high, dtype=np.float32).reshape(-1)
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(low < high)):
            raise AdapterError(
                f"{SUITE}: the action space of {self.env_id} is {space}; rfcl needs finite "
                "bounds with low < high in every dimension (its actions in [-1, 1] are mapped "
                "onto them)"
            )
        return low, high

    def _state_functions(self) -> "_StateFunctions":
        env, wrapped = self._env, self._wrapped
        get = _attr(wrapped, "rfcl_get_state")
        put = _attr(wrapped, "rfcl_set_state")
        if get is not None or put is not None:
            if get is None or put is None:
                missing = "rfcl_get_state" if get is None else "rfcl_set_state"
                raise AdapterError(
                    f"{SUITE}: {self.env_id} has one of rfcl_get_state / rfcl_set_state but not "
                    f"{missing}: both are needed to restore demo states"
                )
            return _ProtocolState(self, wrapped, get, put)
        if hasattr(env, "model") and hasattr(env, "data") and hasattr(env.data, "qpos"):
            return _MujocoState(self, env)
        raise AdapterError(
            f"{SUITE}: {self.env_id} ({type(env).__name__}) cannot save and restore its state: "
            "give it rfcl_get_state() and rfcl_set_state(state) (docs/YOUR_TASK.md), or use a "
            "MuJoCo env, whose state rfcl saves itself"
        )

    def _check_restore(self, state: np.ndarray, obs: np.ndarray) -> None:
        """Set then get must give the state back, and the restored observation the reset's."""
        s = np.asarray(state, dtype=np.float32).reshape(-1)
        restored_obs = self.set_state(s)
        again = self.get_state()
        if again.shape != s.shape:
            raise AdapterError(
                f"{SUITE}: {self.env_id}: after restoring a state of {s.shape[0]} values, its "
                f"state has {again.shape[0]}"
            )
        diff = np.abs(again - s)
        if diff.max(initial=0.0) > RESTORE_TOLERANCE:
            i = int(np.argmax(diff))
            raise AdapterError(
                f"{SUITE}: {self.env_id} does not restore its state: set then get differs by "
                f"{diff[i]:.3g} at entry {i} ({self._entry_name(i)}), more than "
                f"{RESTORE_TOLERANCE:g}"
            )
        if restored_obs.shape != obs.shape:
            raise AdapterError(
                f"{SUITE}: {self.env_id}: the observation of a restored state has "
                f"{restored_obs.shape[0]} values, the reset's {obs.shape[0]}"
            )

    def _entry_name(self, i: int) -> str:
        offset = 0
        for name, _, n in self._layout:
            if i < offset + n:
                return f"{name}[{i - offset}]"
            offset += n
        return "?"

    def _flat_obs(self, obs: Any, where: str) -> np.ndarray:
        from gymnasium import spaces

        if isinstance(obs, (dict, tuple)):
            obs = spaces.flatten(self._obs_space, obs)
        o = np.asarray(obs, dtype=np.float32).reshape(-1)
        if not np.all(np.isfinite(o)):
            raise AdapterError(
                f"{SUITE}: {self.env_id} returned an observation from {where} with a value that "
                f"is not finite: {o.tolist()}"
            )
        expected = getattr(self, "obs_dim", None)
        if expected is not None and o.shape[0] != expected:
            raise AdapterError(
                f"{SUITE}: {self.env_id} returned an observation of {o.shape[0]} values from "
                f"{where}, and of {expected} before"
            )
        return o


def success_of(env_id: str, info: dict[str, Any]) -> bool:
    """``info["success"]``, else ``info["is_success"]``."""
    for key in ("success", "is_success"):
        if key in info:
            return bool(np.asarray(info[key]).reshape(-1)[0])
    raise AdapterError(
        f"{SUITE}: {env_id} reports no 'success' (or 'is_success') in its step info (it has "
        f"{sorted(info)}); rfcl's reward is +1 per success step, so the env must say when it "
        "succeeds, or env.success must name a module:callable(env, obs, info) that does"
    )


def _attr(wrapped: Any, name: str) -> Any:
    """``name`` of the env or of any wrapper around it (outermost first), or ``None``."""
    env = wrapped
    while env is not None:
        value = getattr(type(env), name, None) and getattr(env, name, None)
        if callable(value):
            return value
        env = getattr(env, "env", None)
    return None


def _observation_wrappers(wrapped: Any) -> list[Any]:
    """The observation wrappers around the unwrapped env, innermost first."""
    from gymnasium import ObservationWrapper

    chain, env = [], wrapped
    while hasattr(env, "env"):
        if isinstance(env, ObservationWrapper):
            chain.append(env)
        env = env.env
    return chain[::-1]


class _StateFunctions:
    """How the adapter gets, sets and names an env's state."""

    def __init__(self, adapter: GymnasiumAdapter) -> None:
        self.adapter = adapter
        self.wrappers = _observation_wrappers(adapter._wrapped)

    def get(self) -> np.ndarray:
        raise NotImplementedError

    def set(self, state: np.ndarray) -> Any:
        """Restores ``state``; returns the observation as the outermost wrapper would."""
        raise NotImplementedError

    def layout(self, state: np.ndarray) -> list[tuple[str, str, int]]:
        raise NotImplementedError

    def _wrap(self, obs: Any) -> Any:
        for wrapper in self.wrappers:
            obs = wrapper.observation(obs)
        return obs


class _ProtocolState(_StateFunctions):
    def __init__(self, adapter: GymnasiumAdapter, wrapped: Any, get: Any, put: Any) -> None:
        super().__init__(adapter)
        self._get, self._put = get, put
        self._obs = _attr(wrapped, "rfcl_get_obs")
        self._names = _attr(wrapped, "rfcl_state_layout")

    def get(self) -> np.ndarray:
        return np.asarray(self._get(), dtype=np.float64).reshape(-1)

    def set(self, state: np.ndarray) -> Any:
        obs = self._put(np.asarray(state, dtype=np.float64))
        if obs is None:
            if self._obs is None:
                raise AdapterError(
                    f"{SUITE}: {self.adapter.env_id}: rfcl_set_state returned no observation and "
                    "the env has no rfcl_get_obs(): one of them must give the observation of the "
                    "restored state"
                )
            obs = self._obs()
        return self._wrap(obs)

    def layout(self, state: np.ndarray) -> list[tuple[str, str, int]]:
        n = int(np.asarray(state).size)
        if self._names is None:
            return [("state", "field", n)]
        parts = [(str(name), "field", int(length)) for name, length in self._names()]
        if sum(length for _, _, length in parts) != n:
            raise AdapterError(
                f"{SUITE}: {self.adapter.env_id}: rfcl_state_layout() {parts} adds up to "
                f"{sum(p[2] for p in parts)} values, but rfcl_get_state() has {n}"
            )
        return parts


class _MujocoState(_StateFunctions):
    def __init__(self, adapter: GymnasiumAdapter, env: Any) -> None:
        super().__init__(adapter)
        self.env = env
        model = env.model
        self.fields = [("qpos", int(model.nq)), ("qvel", int(model.nv))]
        if int(model.nmocap) > 0:
            self.fields += [("mocap_pos", 3 * int(model.nmocap)),
                            ("mocap_quat", 4 * int(model.nmocap))]
        if int(model.na) > 0:
            self.fields.append(("act", int(model.na)))
        if not callable(getattr(env, "_get_obs", None)):
            raise AdapterError(
                f"{SUITE}: {adapter.env_id} is a MuJoCo env without _get_obs(): give it "
                "rfcl_get_state(), rfcl_set_state(state) and rfcl_get_obs() (docs/YOUR_TASK.md)"
            )

    def get(self) -> np.ndarray:
        data = self.env.data
        return np.concatenate([np.asarray(getattr(data, name)).reshape(-1)
                               for name, _ in self.fields])

    def set(self, state: np.ndarray) -> Any:
        import mujoco

        data, offset = self.env.data, 0
        for name, n in self.fields:
            target = getattr(data, name)
            target[...] = np.asarray(state[offset:offset + n], dtype=np.float64).reshape(
                target.shape)
            offset += n
        # A restored state starts without the solver's warm start, as a reset does.
        data.qacc_warmstart[:] = 0.0
        mujoco.mj_forward(self.env.model, data)
        try:
            obs = self.env._get_obs()
        except TypeError as e:
            raise AdapterError(
                f"{SUITE}: {self.adapter.env_id}'s _get_obs() cannot be called without arguments "
                f"({e}), so rfcl cannot observe a restored state: give the env (or a wrapper) "
                "rfcl_get_state(), rfcl_set_state(state) and rfcl_get_obs() (docs/YOUR_TASK.md)"
            ) from e
        return self._wrap(obs)

    def layout(self, state: np.ndarray) -> list[tuple[str, str, int]]:
        return [(name, "field", n) for name, n in self.fields]
