"""Small Gymnasium envs that break one rule each of the ``gymnasium`` suite (test_gymnasium.py
makes them through ``module:callable`` env ids)."""
from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class Toy(gym.Env):
    """A well-behaved env with the rfcl state protocol: a point that moves by its action."""

    def __init__(self, action_space=None, nan_obs: bool = False, lossy: bool = False,
                 protocol: str = "both", success: bool = True) -> None:
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(3,), dtype=np.float32)
        self.action_space = action_space or spaces.Box(-2.0, 2.0, shape=(2,), dtype=np.float32)
        self.x = np.zeros(3)
        self.nan_obs, self.lossy, self.success = nan_obs, lossy, success
        if protocol != "both":
            # Hide one of the two methods from the class the adapter looks at.
            cls = type(f"Toy_{protocol}", (Toy,), {f"rfcl_{protocol}_state": None})
            self.__class__ = cls

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = self.np_random.uniform(-1.0, 1.0, size=3)
        return self._obs(), {}

    def step(self, action):
        self.x[:2] += np.asarray(action, dtype=np.float64)
        info = {"success": bool(self.x[0] > 1.0)} if self.success else {}
        return self._obs(), 0.0, False, False, info

    def _obs(self):
        obs = self.x.astype(np.float32)
        if self.nan_obs:
            obs[1] = np.nan
        return obs

    def rfcl_get_state(self):
        return self.x.copy()

    def rfcl_set_state(self, state):
        self.x = np.asarray(state, dtype=np.float64).copy()
        if self.lossy:
            self.x[2] = 0.0  # forgets part of the state
        return self._obs()


class NoState(gym.Env):
    """A Gymnasium env with no way to save or restore its state."""

    def __init__(self) -> None:
        self.observation_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, dtype=np.float32), {}

    def step(self, action):
        return np.zeros(2, dtype=np.float32), 0.0, False, False, {"success": False}


def toy(**kwargs):
    return Toy(**kwargs)


def discrete():
    return Toy(action_space=spaces.Discrete(3))


def unbounded():
    return Toy(action_space=spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32))


def pendulum_upright(env, obs, info) -> bool:
    """Success for Gymnasium's InvertedPendulum-v5, which reports none: the pole within 0.05 rad
    of upright and the cart within 0.1 of the centre."""
    return bool(abs(float(env.data.qpos[1])) < 0.05 and abs(float(env.data.qpos[0])) < 0.1)
