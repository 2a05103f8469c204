"""The MetaWorld adapter (rfcl_sim.adapters.metaworld) against the adapter contract and spec 7.3."""
import warnings

import numpy as np
import pytest

from rfcl_sim import adapters
from rfcl_sim.adapters import AdapterError

from adapter_checks import assert_same_rollouts, envs_fixture, rollout

warnings.filterwarnings("ignore", module="gymnasium")

#: Three tasks with different objects: a puck, a stick with a container, a peg with a ring.
TASKS = ["pick-place-v3", "stick-pull-v3", "assembly-v3"]


envs = envs_fixture("metaworld", TASKS)


def test_dims_horizon_and_layout_follow_spec(envs):
    env = envs["pick-place-v3"]
    assert (env.suite, env.env_id, env.obs_dim, env.action_dim, env.horizon) == (
        "metaworld", "pick-place-v3", 39, 4, 200)
    layout = env.state_layout()
    assert [name for name, _, _ in layout] == [
        "qpos", "qvel", "mocap_pos", "mocap_quat", "rand_vec", "prev_frame"]
    assert all(kind == "field" for _, kind, _ in layout)
    assert env.state_dim == env.get_state().shape[0] == sum(n for _, _, n in layout)
    obs = env.reset(3, {})
    assert obs.dtype == np.float32 and obs.shape == (39,)
    # Goal-observable: the last 3 values are the goal, which MetaWorld hides with zeros otherwise.
    assert np.abs(obs[-3:]).sum() > 0


def test_reset_is_deterministic_per_seed_and_seeds_differ(envs):
    env = envs["pick-place-v3"]
    first, state = env.reset(11, {}), env.get_state()
    env.step(np.ones(4, dtype=np.float32))
    assert np.array_equal(env.reset(11, {}), first)
    assert np.array_equal(env.get_state(), state)
    assert not np.allclose(env.reset(12, {}), first)


def test_unseeded_resets_follow_the_adapter_seed():
    a, b = (adapters.make("metaworld", "push-v3", seed=5) for _ in range(2))
    try:
        for _ in range(2):
            assert np.array_equal(a.reset(None, {}), b.reset(None, {}))
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize("task", TASKS)
def test_state_round_trip_and_stepping_from_a_restored_state(envs, task):
    env = envs[task]
    rng = np.random.default_rng(1)
    env.reset(21, {})
    rollout(env, rng.uniform(-1, 1, (25, 4)).astype(np.float32))
    state = env.get_state()
    obs = env._obs.copy()
    actions = rng.uniform(-1, 1, (10, 4)).astype(np.float32)
    original = rollout(env, actions)

    # Restore after a reset to another seed: the state carries the task's random vector.
    env.reset(99, {})
    restored_obs = env.set_state(state)
    assert np.array_equal(env.get_state(), state)
    np.testing.assert_allclose(restored_obs, obs, atol=1e-6)
    restored = rollout(env, actions)
    assert_same_rollouts(original, restored, atol=1e-4)

    # A second restore is bit-identical to the first: set_state does not depend on history.
    env.reset(21, {})
    env.set_state(state)
    assert_same_rollouts(restored, rollout(env, actions))


def test_stepping_past_metaworld_path_limit_is_allowed():
    env = adapters.make("metaworld", "reach-v3", max_episode_steps=50)
    try:
        assert env.horizon == 50
        env.reset(0, {})
        for _ in range(510):  # MetaWorld itself refuses step 501; rfcl owns time limits
            env.step(np.zeros(4, dtype=np.float32))
    finally:
        env.close()


def test_bad_input_is_refused_with_a_clear_message(envs):
    env = envs["pick-place-v3"]
    with pytest.raises(AdapterError, match="action has 3 components"):
        env.step(np.zeros(3))
    with pytest.raises(AdapterError, match="state has 5 values"):
        env.set_state(np.zeros(5))
    bad = env.get_state()
    bad[0] = np.nan
    with pytest.raises(AdapterError, match="state field 'qpos'"):
        env.set_state(bad)
    with pytest.raises(AdapterError, match="reset options"):
        env.reset(0, {"initial_state_dict": {}})
    with pytest.raises(AdapterError, match="unknown task 'pick-place-v2'"):
        adapters.make("metaworld", "pick-place-v2")
    with pytest.raises(AdapterError, match="unknown argument"):
        adapters.make("metaworld", "pick-place-v3", obs_mode="rgb")
    with pytest.raises(AdapterError, match="control_mode 'pd_joint_delta_pos'"):
        adapters.make("metaworld", "pick-place-v3", control_mode="pd_joint_delta_pos")
    with pytest.raises(AdapterError, match="env_kwargs"):
        adapters.make("metaworld", "pick-place-v3", env_kwargs={"use_one_hot": True})


def load_preset(path):
    """A preset with its base_config chain merged in (later files win, mappings merge)."""
    yaml = pytest.importorskip("yaml")

    def merge(into, new):
        for k, v in new.items():
            if isinstance(v, dict) and isinstance(into.get(k), dict):
                merge(into[k], v)
            else:
                into[k] = v
        return into

    raw = yaml.safe_load(path.read_text())
    resolved = {}
    for base in raw.pop("base_config", []):
        merge(resolved, load_preset((path.parent / base).resolve()))
    return merge(resolved, raw)


def test_every_preset_names_a_task_with_a_scripted_policy_and_the_adapter_dims(envs):
    from pathlib import Path

    from metaworld.policies import ENV_POLICY_MAP

    configs = Path(__file__).resolve().parents[2] / "configs" / "metaworld"
    presets = sorted(configs.glob("*.yml"))
    assert len(presets) == 30  # 15 tasks x 2 sets (spec 8.2, 8.3)
    env = envs["pick-place-v3"]
    for path in presets:
        c = load_preset(path)["env"]
        assert c["suite"] == "metaworld", path
        assert c["env_id"] in ENV_POLICY_MAP, path  # `rfcl_sim.demos metaworld` can make demos
        assert (c["obs_dim"], c["action_dim"], c["max_episode_steps"]) == (
            env.obs_dim, env.action_dim, env.horizon), path


def test_state_matches_metaworlds_own_state(envs):
    env = envs["stick-pull-v3"]
    env.reset(4, {})
    rollout(env, np.full((5, 4), 0.5, dtype=np.float32))
    qpos, qvel = env._env.get_env_state()
    parts = env._split(env.get_state())
    np.testing.assert_allclose(parts["qpos"], qpos, atol=1e-6)
    np.testing.assert_allclose(parts["qvel"], qvel, atol=1e-5)
    np.testing.assert_allclose(parts["mocap_pos"], env._env.data.mocap_pos[0], atol=1e-6)
    np.testing.assert_allclose(parts["rand_vec"], env._env._last_rand_vec, atol=1e-6)
    np.testing.assert_array_equal(parts["prev_frame"], env._obs[18:36])


def test_reset_takes_any_u64_seed(envs):
    env = envs["assembly-v3"]  # Rust seeds are u64
    assert np.array_equal(env.reset(2**64 - 1, {}), env.reset(np.uint64(2**64 - 1), {}))
    with pytest.raises(AdapterError, match="non-negative integer"):
        env.reset(-1, {})
