"""Fixtures and checks that the tests of the MuJoCo field adapters (test_adroit.py,
test_metaworld.py) share."""
import numpy as np
import pytest

from rfcl_sim import adapters


def envs_fixture(suite, tasks):
    """A module-scoped fixture of ``{task: adapter}``: one adapter of ``suite`` (made with seed 0)
    per task, shared by the module's tests, as making one takes a while, and closed after them."""

    @pytest.fixture(scope="module")
    def envs():
        made = {task: adapters.make(suite, task, seed=0) for task in tasks}
        yield made
        for env in made.values():
            env.close()

    return envs


def rollout(env, actions):
    """The ``(observation, success)`` of each step of ``actions``."""
    return [env.step(a) for a in actions]


def assert_same_rollouts(expected, actual, atol=None):
    """The same successes step by step, and observations within ``atol`` (``None``: bit for
    bit)."""
    assert len(actual) == len(expected)
    for (o1, s1), (o2, s2) in zip(expected, actual):
        if atol is None:
            assert np.array_equal(o2, o1)
        else:
            np.testing.assert_allclose(o2, o1, atol=atol)
        assert s1 == s2
