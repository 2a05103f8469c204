"""Demos for a stock Gymnasium-Robotics MuJoCo env that rfcl runs with no code of yours:
FetchReach-v4 (docs/YOUR_TASK.md, "A MuJoCo env with no code"). The env needs nothing; only the
demos need a policy, and this scripted one moves the gripper straight to the goal.

The gymnasium suite flattens FetchReach's dict observation in its keys' order: achieved_goal (3),
desired_goal (3), observation (10).
"""
from __future__ import annotations

import numpy as np


def scripted_policy(obs: np.ndarray) -> np.ndarray:
    """Gripper displacement toward the goal, in [-1, 1]; the fingers stay (action 3 = 0)."""
    achieved, desired = obs[0:3], obs[3:6]
    move = np.clip(10.0 * (desired - achieved), -1.0, 1.0)
    return np.concatenate([move, [0.0]]).astype(np.float32)
