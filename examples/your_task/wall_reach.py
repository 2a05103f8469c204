"""WallReach-v0: a task rfcl does not know, written against Gymnasium's API (docs/YOUR_TASK.md).

A point in the square [-1, 1]² must reach a goal on the other side of a wall. The wall is the
segment x = 0, -0.6 <= y <= 1: the only way through is the gap below it, so a policy that heads
straight for the goal gets stuck, and a sparse reward gives it nothing to learn from until it
finds the gap. That is the situation reverse curricula are for.

* Observation: position (2), velocity (2), goal (2).
* Action: an acceleration in [-1, 1]², applied for ``DT`` seconds; the velocity is damped and
  clipped, the point stops at the square's edges and at the wall.
* Success: the point within ``GOAL_RADIUS`` of the goal (every step it is there).
* Reset: the start is drawn in the left half, the goal in the right half, from the seed.

For rfcl, the env implements the state protocol of ``env.suite: gymnasium``: ``rfcl_get_state``
(position, velocity, goal as one vector), ``rfcl_set_state`` (restores it and returns the
observation) and ``rfcl_state_layout`` (names the parts, so that ``rfcl demos inspect --replay``
judges positions and velocities each with their own tolerance). ``scripted_policy`` drives it to
the goal through the gap: ``rfcl demos record --policy wall_reach:scripted_policy`` records demos
with it.
"""
from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

DT = 0.1
MAX_SPEED = 1.0
DAMPING = 0.9
GOAL_RADIUS = 0.1
#: The wall: x = 0 from y = WALL_BOTTOM up to the top edge.
WALL_BOTTOM = -0.6


class WallReach(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self) -> None:
        self.observation_space = spaces.Box(-2.0, 2.0, shape=(6,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.pos = np.zeros(2)
        self.vel = np.zeros(2)
        self.goal = np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        rng = self.np_random
        self.pos = np.array([rng.uniform(-0.9, -0.2), rng.uniform(-0.2, 0.9)])
        self.vel = np.zeros(2)
        self.goal = np.array([rng.uniform(0.2, 0.9), rng.uniform(-0.2, 0.9)])
        return self._obs(), {}

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self.vel = np.clip(DAMPING * self.vel + DT * 2.0 * a, -MAX_SPEED, MAX_SPEED)
        new = np.clip(self.pos + DT * self.vel, -1.0, 1.0)
        crosses = (self.pos[0] < 0.0) != (new[0] < 0.0)
        if crosses:
            # Where the path meets x = 0: through the gap below the wall, or stopped at the wall.
            t = self.pos[0] / (self.pos[0] - new[0])
            y = self.pos[1] + t * (new[1] - self.pos[1])
            if y > WALL_BOTTOM:
                new[0] = -1e-3 if self.pos[0] < 0.0 else 1e-3
                self.vel[0] = 0.0
        self.pos = new
        success = bool(np.linalg.norm(self.pos - self.goal) < GOAL_RADIUS)
        return self._obs(), float(success), False, False, {"success": success}

    def _obs(self) -> np.ndarray:
        return np.concatenate([self.pos, self.vel, self.goal]).astype(np.float32)

    # The rfcl state protocol (docs/YOUR_TASK.md) ---------------------------------------------

    def rfcl_get_state(self) -> np.ndarray:
        return np.concatenate([self.pos, self.vel, self.goal])

    def rfcl_set_state(self, state) -> np.ndarray:
        state = np.asarray(state, dtype=np.float64)
        if np.any(np.abs(state[0:2]) > 1.0):
            # A state the env cannot be in: refused, and rfcl counts it against its demo.
            raise ValueError(f"pos {state[0:2]} is outside the arena [-1, 1]²")
        self.pos, self.vel, self.goal = state[0:2].copy(), state[2:4].copy(), state[4:6].copy()
        return self._obs()

    def rfcl_state_layout(self):
        return [("pos", 2), ("vel", 2), ("goal", 2)]


def scripted_policy(obs: np.ndarray) -> np.ndarray:
    """Heads for the gap below the wall, then for the goal: actions in [-1, 1]²."""
    pos, vel, goal = obs[0:2], obs[2:4], obs[4:6]
    if pos[0] < 0.0 and pos[1] > WALL_BOTTOM - 0.1:
        target = np.array([-0.15, WALL_BOTTOM - 0.25])  # below the wall's end, left of it
    elif pos[0] < 0.15 and pos[1] < WALL_BOTTOM:
        target = np.array([0.3, WALL_BOTTOM - 0.2])  # through the gap
    else:
        target = goal
    return np.clip(3.0 * (target - pos) - 1.5 * vel, -1.0, 1.0).astype(np.float32)


gym.register(id="WallReach-v0", entry_point=WallReach, max_episode_steps=100)
