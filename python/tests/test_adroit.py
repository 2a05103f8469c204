"""The Adroit adapter (rfcl_sim.adapters.adroit) against the adapter contract and spec 7.4."""
import warnings

import numpy as np
import pytest

from rfcl_sim import adapters
from rfcl_sim.adapters import AdapterError

from adapter_checks import assert_same_rollouts, envs_fixture, rollout

warnings.filterwarnings("ignore", module="gymnasium")
warnings.filterwarnings("ignore", module="gymnasium_robotics")

#: env id -> (obs dim, action dim, horizon, task fields): spec 7.4 and 8.3.
TASKS = {
    "AdroitHandDoorSparse-v1": (39, 28, 200, ["door_body_pos"]),
    "AdroitHandPenSparse-v1": (45, 24, 100, ["desired_orien"]),
    "AdroitHandRelocateSparse-v1": (39, 30, 200, ["obj_pos", "target_pos"]),
}


envs = envs_fixture("adroit", TASKS)


@pytest.mark.parametrize("task", TASKS)
def test_dims_horizon_and_layout_follow_spec(envs, task):
    env = envs[task]
    obs_dim, action_dim, horizon, fields = TASKS[task]
    assert (env.obs_dim, env.action_dim, env.horizon) == (obs_dim, action_dim, horizon)
    layout = env.state_layout()
    assert [name for name, _, _ in layout] == ["qpos", "qvel", *fields]
    assert all(kind == "field" for _, kind, _ in layout)
    assert env.get_state().shape == (env.state_dim,)
    assert env.reset(0, {}).shape == (obs_dim,)


@pytest.mark.parametrize("task", TASKS)
def test_state_round_trip_and_stepping_from_a_restored_state(envs, task):
    env = envs[task]
    rng = np.random.default_rng(2)
    env.reset(7, {})
    rollout(env, rng.uniform(-1, 1, (20, env.action_dim)))
    state = env.get_state()
    actions = rng.uniform(-1, 1, (10, env.action_dim)).astype(np.float32)
    original = rollout(env, actions)

    # Restored after a reset to another seed: the state carries the randomised door / goal / ball.
    env.reset(1234, {})
    env.set_state(state)
    assert np.array_equal(env.get_state(), state)
    restored = rollout(env, actions)
    assert_same_rollouts(original, restored, atol=1e-4)

    env.reset(7, {})
    env.set_state(state)
    assert_same_rollouts(restored, rollout(env, actions))


@pytest.mark.parametrize("task", TASKS)
def test_reset_is_seeded_and_takes_an_initial_state_dict(envs, task):
    env = envs[task]
    first = env.reset(3, {})
    state = env.get_state()
    assert np.array_equal(env.reset(3, {}), first)
    assert not np.allclose(env.reset(4, {}), first)
    # options.initial_state_dict (how gymnasium-robotics and the human demos give a start state).
    obs = env.reset(4, {"initial_state_dict": env.state_to_dict(state)})
    assert np.array_equal(env.get_state(), state)
    np.testing.assert_allclose(obs, first, atol=1e-6)  # the state holds float32 values


def test_success_comes_from_the_env():
    env = adapters.make("adroit", "door")
    try:
        env.reset(0, {})
        state = env.get_state()
        hinge = env._env.door_hinge_addrs
        open_state = state.copy()
        open_state[hinge] = 1.5  # spec 7.4: the door counts as open from 1.35 rad
        env.set_state(open_state)
        assert env.step(np.zeros(env.action_dim))[1] is True
        env.set_state(state)
        assert env.step(np.zeros(env.action_dim))[1] is False
    finally:
        env.close()


def test_relocate_state_holds_model_positions():
    """The env's own get_env_state reports the ball's world position, which set_env_state writes as
    a model position; our state holds the model position, and relocate_model_pos converts."""
    env = adapters.make("adroit", "AdroitHandRelocate-v1")  # the dense id: same task
    try:
        assert env.env_id == "AdroitHandRelocateSparse-v1"
        env.reset(5, {})
        rollout(env, np.full((15, env.action_dim), 0.3, dtype=np.float32))
        inner = env._env
        qpos = inner.data.qpos.copy()
        qpos[30:33] += [0.02, -0.01, 0.03]  # move the ball along its joints
        state = env.get_state()
        state[:36] = qpos
        env.set_state(state)
        world = inner.data.xpos[inner.obj_body_id].copy()
        target_world = inner.data.site_xpos[inner.target_obj_site_id].copy()
        model_pos, target_pos = env.relocate_model_pos(qpos, world, target_world)
        np.testing.assert_allclose(model_pos, state[72:75], atol=1e-6)
        np.testing.assert_allclose(target_pos, state[75:78], atol=1e-6)
    finally:
        env.close()


def test_bad_input_is_refused_with_a_clear_message(envs):
    env = envs["AdroitHandDoorSparse-v1"]
    with pytest.raises(AdapterError, match="action has 4 components"):
        env.step(np.zeros(4))
    with pytest.raises(AdapterError, match="state has 3 values"):
        env.set_state(np.zeros(3))
    with pytest.raises(AdapterError, match="lacks 'door_body_pos'"):
        env.reset(0, {"initial_state_dict": {"qpos": [0.0] * 30, "qvel": [0.0] * 30}})
    with pytest.raises(AdapterError, match=r"\['qvel'\] has 2 values"):
        env.reset(0, {"initial_state_dict": {"qpos": [0.0] * 30, "qvel": [0.0] * 2,
                                             "door_body_pos": [0.0] * 3}})
    with pytest.raises(AdapterError, match="reset options"):
        env.reset(0, {"seed": 3})
    with pytest.raises(AdapterError, match="unknown env 'AdroitHandHammerSparse-v1'"):
        adapters.make("adroit", "AdroitHandHammerSparse-v1")
    with pytest.raises(AdapterError, match="max_episode_steps"):
        adapters.make("adroit", "pen", max_episode_steps=0)


def test_every_preset_has_the_adapter_dims_and_horizon(envs):
    from pathlib import Path

    yaml = pytest.importorskip("yaml")
    configs = Path(__file__).resolve().parents[2] / "configs"
    presets = sorted((configs / "adroit").glob("*.yml"))
    assert len(presets) == 6  # 3 tasks x 2 sets (spec 8.2, 8.3)
    base = yaml.safe_load((configs / "base" / "adroit.yml").read_text())["env"]
    for path in presets:
        c = {**base, **yaml.safe_load(path.read_text())["env"]}
        env = envs[c["env_id"]]
        assert (c["obs_dim"], c["action_dim"], c["max_episode_steps"]) == (
            env.obs_dim, env.action_dim, env.horizon), path


@pytest.mark.parametrize("task", TASKS)
def test_state_matches_the_envs_own_state_dict(envs, task):
    env = envs[task]
    env.reset(8, {})
    rollout(env, np.full((5, env.action_dim), -0.4, dtype=np.float32))
    own = env._env.get_env_state()
    ours = env._split(env.get_state())
    for name in ours:
        if name == "obj_pos":  # Relocate: ours is the model position (module docs)
            continue
        np.testing.assert_allclose(ours[name], own[name], atol=1e-6, err_msg=name)


def test_reset_takes_any_u64_seed(envs):
    env = envs["AdroitHandPenSparse-v1"]  # Rust seeds are u64
    assert np.array_equal(env.reset(2**64 - 1, {}), env.reset(np.uint64(2**64 - 1), {}))
    with pytest.raises(AdapterError, match="non-negative integer"):
        env.reset(1.5, {})
