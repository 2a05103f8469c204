"""A ManiSkill3 task of a user's own package, registered on import (test_maniskill.py lists this
module in the adapter's ``imports``, as a run config's ``env.imports`` does)."""
from mani_skill.envs.tasks import PickCubeEnv
from mani_skill.utils.registration import register_env


@register_env("YourPickCube-v1", max_episode_steps=40)
class YourPickCube(PickCubeEnv):
    """PickCube with a goal that must be reached more precisely: a task ManiSkill does not ship."""

    goal_thresh = 0.02
