"""The ``gymnasium`` suite: your own task with nothing but Python and YAML.

* WallReach-v0 (examples/your_task, the tutorial's env) through ``env.imports`` and through a
  ``module:callable`` env id: its state protocol, exact restores, its success flag, actions mapped
  onto its action box;
* FetchReach-v4 from Gymnasium-Robotics with no code of ours: rfcl's own MuJoCo state functions
  (qpos, qvel, mocap), a restored state that steps as the original;
* every bad case of the suite's start-up checks, one clear line each.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from rfcl_sim.adapters import AdapterError, make

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "your_task"
TESTS = Path(__file__).resolve().parent
for path in (EXAMPLE, TESTS):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))


def test_your_env_through_imports_and_an_entry_point():
    # The registered horizon, or the one the config gives an entry point.
    for env_id, kwargs, horizon in [("WallReach-v0", {"imports": ["wall_reach"]}, 100),
                                    ("wall_reach:WallReach", {"max_episode_steps": 60}, 60)]:
        a = make("gymnasium", env_id, **kwargs)
        assert (a.obs_dim, a.action_dim, a.horizon) == (6, 2, horizon)
        assert a.state_layout() == [("pos", "field", 2), ("vel", "field", 2), ("goal", "field", 2)]
        obs = a.reset(5, {})
        state = a.get_state()
        np.testing.assert_array_equal(obs, state)  # this env observes its whole state
        for _ in range(3):
            obs, success = a.step(np.array([1.0, -1.0], dtype=np.float32))
            assert not success
        # Restore after the reset to the same seed: the same state and observation.
        a.reset(5, {})
        np.testing.assert_array_equal(a.set_state(obs), obs)
        np.testing.assert_array_equal(a.get_state(), obs)
        # A state at the goal is a success after one more step.
        at_goal = state.copy()
        at_goal[0:2], at_goal[2:4] = state[4:6], 0.0
        a.set_state(at_goal)
        assert a.step(np.zeros(2, dtype=np.float32))[1]
        a.close()


def test_the_scripted_policy_reaches_the_goal_through_the_adapter():
    import wall_reach

    a = make("gymnasium", "WallReach-v0", imports=["wall_reach"])
    for seed in range(5):
        obs, success = a.reset(seed, {}), False
        for _ in range(a.horizon):
            obs, success = a.step(wall_reach.scripted_policy(obs))
            if success:
                break
        assert success, seed


def test_actions_in_minus_one_one_map_onto_the_action_box():
    a = make("gymnasium", "gym_fixtures:toy", max_episode_steps=10)
    a.reset(0, {})
    before = a.get_state()
    a.step(np.array([1.0, -0.5], dtype=np.float32))  # box [-2, 2]: moves by (2, -1)
    np.testing.assert_allclose(a.get_state()[:2] - before[:2], [2.0, -1.0], atol=1e-6)


def test_a_stock_mujoco_env_needs_no_code():
    """FetchReach-v4: rfcl saves and restores qpos, qvel and the mocap body itself; its goal comes
    from the reset seed, its dict observation is flattened, its success is info['is_success']."""
    a = make("gymnasium", "FetchReach-v4", imports=["gymnasium_robotics"])
    assert [name for name, _, _ in a.state_layout()] == ["qpos", "qvel", "mocap_pos", "mocap_quat"]
    assert a.obs_dim == 16 and a.action_dim == 4
    a.reset(11, {})
    actions = [np.array([0.5, -0.3, 0.2, 1.0], dtype=np.float32)] * 4
    for action in actions[:2]:
        a.step(action)
    mid = a.get_state()
    original = [a.step(action)[0] for action in actions[2:]]
    a.reset(11, {})
    a.set_state(mid)
    np.testing.assert_allclose(a.get_state(), mid, atol=1e-6)
    replayed = [a.step(action)[0] for action in actions[2:]]
    np.testing.assert_allclose(replayed, original, atol=1e-5)
    a.close()


@pytest.mark.parametrize("env_id, kwargs, message", [
    ("gym_fixtures:NoState", {}, "cannot save and restore its state: give it rfcl_get_state()"),
    ("gym_fixtures:discrete", {}, "the action space of gym_fixtures:discrete is Discrete(3); "
                                  "rfcl needs a bounded Box"),
    ("gym_fixtures:unbounded", {}, "rfcl needs finite bounds"),
    ("gym_fixtures:toy", {"env_kwargs": {"nan_obs": True}},
     "returned an observation from reset with a value that is not finite"),
    ("gym_fixtures:toy", {"env_kwargs": {"lossy": True}},
     "does not restore its state: set then get differs by"),
    ("gym_fixtures:toy", {"env_kwargs": {"protocol": "set"}},
     "has one of rfcl_get_state / rfcl_set_state but not rfcl_set_state"),
    ("WallReach-v0", {"imports": ["no_such_module_of_yours"]},
     "env.imports: importing 'no_such_module_of_yours' failed (ModuleNotFoundError"),
    ("NoSuchEnv-v0", {}, "gymnasium cannot make 'NoSuchEnv-v0'"),
    ("gym_fixtures:toy", {"max_episode_steps": 0}, "max_episode_steps must be a positive integer"),
    ("gym_fixtures:missing", {}, "'gym_fixtures' has no 'missing'"),
])
def test_bad_envs_are_refused_in_one_line(env_id, kwargs, message):
    with pytest.raises(AdapterError) as err:
        make("gymnasium", env_id, **{"max_episode_steps": 10, **kwargs})
    text = str(err.value)
    assert message in text and "\n" not in text, text
    assert text.startswith("gymnasium: "), text


def test_a_success_callable_serves_an_env_that_reports_none():
    """Gymnasium's own InvertedPendulum-v5: no success in its info, rfcl's MuJoCo state, and the
    success of the callable the config names (env.success)."""
    a = make("gymnasium", "InvertedPendulum-v5", success="gym_fixtures:pendulum_upright")
    assert [name for name, _, _ in a.state_layout()] == ["qpos", "qvel"]
    a.reset(1, {})
    upright = np.zeros(4, dtype=np.float32)
    a.set_state(upright)
    assert a.step(np.zeros(1, dtype=np.float32))[1]
    tilted = upright.copy()
    tilted[1] = 0.15
    a.reset(1, {})
    a.set_state(tilted)
    assert not a.step(np.zeros(1, dtype=np.float32))[1]
    with pytest.raises(AdapterError, match="'gym_fixtures' has no 'nothing'"):
        make("gymnasium", "InvertedPendulum-v5", success="gym_fixtures:nothing")


def test_an_env_that_never_says_success_is_named_at_its_first_step():
    a = make("gymnasium", "gym_fixtures:toy", max_episode_steps=10, env_kwargs={"success": False})
    a.reset(0, {})
    with pytest.raises(AdapterError, match="reports no 'success' \\(or 'is_success'\\) in its step.*env.success"):
        a.step(np.zeros(2, dtype=np.float32))


def test_the_lossy_entry_is_named():
    with pytest.raises(AdapterError, match=r"at entry 2 \(state\[2\]\)"):
        make("gymnasium", "gym_fixtures:toy", max_episode_steps=10, env_kwargs={"lossy": True})


def test_record_writes_your_policys_successful_episodes(tmp_path):
    from rfcl_sim import demo_file, demos

    out = tmp_path / "wall_reach.h5"
    options = {"imports": ["wall_reach"], "max_episode_steps": 60}
    kept = demos.record("gymnasium", "WallReach-v0", options, "wall_reach:scripted_policy", 3,
                        out, log=lambda line: None)
    env_info, layout, trajs = demo_file.read(out)
    assert env_info["suite"] == "gymnasium" and env_info["max_episode_steps"] == 60
    assert layout == [("pos", "field", 2), ("vel", "field", 2), ("goal", "field", 2)]
    assert [t.seed for t in trajs] == [0, 1, 2] and all(t.succeeded for t in trajs)
    np.testing.assert_array_equal(trajs[1].states, kept[1].states.astype(np.float32))


@pytest.mark.parametrize("policy, message", [
    ("wall_reach", "expected module:callable"),
    ("wall_reach:no_such_policy", "'wall_reach' has no 'no_such_policy'"),
    ("no_such_module:act", "importing 'no_such_module' failed"),
])
def test_record_names_a_policy_it_cannot_use(tmp_path, policy, message):
    from rfcl_sim import demos

    with pytest.raises(demos.DemoSourceError, match=message):
        demos.record("gymnasium", "WallReach-v0", {"imports": ["wall_reach"]}, policy, 1,
                     tmp_path / "x.h5", log=lambda line: None)
