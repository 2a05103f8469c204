"""The ManiSkill3 adapter against the simulator's own state (spec 7.1, 12.13)."""
import numpy as np
import pytest

from rfcl_sim import adapters
from rfcl_sim.adapters.base import AdapterError
from rfcl_sim.adapters.maniskill import fold_seed

TASKS = ["PickCube-v1", "StackCube-v1", "PegInsertionSide-v1", "PlugCharger-v1"]


def _flat(state_dict):
    """The simulator's state dict flattened in the documented order, straight from the tensors."""
    parts = [v.numpy().reshape(-1) for v in state_dict["actors"].values()]
    parts += [v.numpy().reshape(-1) for v in state_dict["articulations"].values()]
    return np.concatenate(parts)


@pytest.mark.parametrize("env_id", TASKS)
def test_state_round_trip_matches_the_simulator(env_id):
    ad = adapters.make("maniskill3", env_id, seed=1)
    sim = ad._env
    # Layout: actors then articulations, in the state dict's (registration) order.
    sd = sim.get_state_dict()
    names = [f"actors/{n}" for n in sd["actors"]] + [f"articulations/{n}" for n in sd["articulations"]]
    assert [name for name, _, _ in ad.state_layout()] == names
    assert [kind for _, kind, _ in ad.state_layout()] == ["actor"] * len(sd["actors"]) + [
        "articulation"
    ] * len(sd["articulations"])
    assert all(n == 13 for _, kind, n in ad.state_layout() if kind == "actor")
    assert ad.state_dim == sim.get_state().shape[1]

    # A state with motion in it: a few random steps from seed 5.
    rng = np.random.default_rng(0)
    ad.reset(5, {})
    for _ in range(5):
        obs, success = ad.step(rng.uniform(-1, 1, ad.action_dim).astype(np.float32))
        assert obs.shape == (ad.obs_dim,) and obs.dtype == np.float32 and isinstance(success, bool)
    state = ad.get_state()
    np.testing.assert_array_equal(state, _flat(sim.get_state_dict()))
    np.testing.assert_array_equal(state, sim.get_state()[0].numpy())
    obs_there = sim.get_obs()[0].numpy()

    # Set it after a reset to the same seed (spec 12.13) and read it back through the simulator.
    ad.reset(5, {})
    obs = ad.set_state(state)
    np.testing.assert_allclose(_flat(sim.get_state_dict()), state, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ad.get_state(), state, rtol=0, atol=1e-6)
    assert obs.shape == (ad.obs_dim,)
    # Pose- and velocity-derived observations come back (contact-derived ones need a physics step).
    np.testing.assert_allclose(obs[:18], obs_there[:18], atol=1e-5)
    ad.close()


def test_seeded_resets_are_deterministic_and_unseeded_ones_continue_a_chain():
    ad = adapters.make("maniskill3", "PickCube-v1", seed=7)
    a = ad.reset(3, {})
    ad.reset(None, {})
    b = ad.reset(3, {})
    np.testing.assert_array_equal(a, b)
    c, d = ad.reset(None, {}), ad.reset(None, {})
    assert not np.array_equal(c, d)
    # A held-out eval seed (>= 2**40) is accepted and differs from the small seeds.
    e = ad.reset(2**40, {})
    assert not np.array_equal(e, ad.reset(0, {}))
    assert fold_seed(5) == 5 and 2**31 <= fold_seed(2**40) < 2**32
    ad.close()


def test_bad_input_is_named():
    with pytest.raises(AdapterError, match="no env 'NoSuchCube-v1'"):
        adapters.make("maniskill3", "NoSuchCube-v1")
    with pytest.raises(AdapterError, match="unknown option"):
        adapters.make("maniskill3", "PickCube-v1", obs_mode="rgb")
    ad = adapters.make("maniskill3", "PickCube-v1")
    assert (ad.obs_dim, ad.action_dim, ad.horizon) == (42, 8, 50)
    with pytest.raises(AdapterError, match="action has 3 components, PickCube-v1 takes 8"):
        ad.step(np.zeros(3, np.float32))
    with pytest.raises(AdapterError, match="state has 2 values"):
        ad.set_state(np.zeros(2, np.float32))
    ad.close()


def test_the_bridge_speaks_frames_and_never_raises():
    import json
    import struct

    from rfcl_sim import bridge as b

    br = b.Bridge("maniskill3", "PickCube-v1", json.dumps({"max_episode_steps": 50}))
    status, hello = br.handle(b.OP_HELLO, b"")
    info = json.loads(hello)
    assert status == b.STATUS_OK and (info["obs_dim"], info["action_dim"], info["horizon"]) == (42, 8, 50)
    assert [n for n, _, _ in info["state_layout"]][-1] == "articulations/panda"

    def reset(seed, options=b"{}", state=b""):
        return br.handle(b.OP_RESET, struct.pack("<BQI", 1, seed, len(options)) + options + state)

    status, obs = reset(3)
    assert status == b.STATUS_OK and len(obs) == 42 * 4
    status, out = br.handle(b.OP_STEP, np.zeros(8, "<f4").tobytes())
    assert status == b.STATUS_OK and out[0] in (0, 1) and len(out) == 1 + 42 * 4
    status, state = br.handle(b.OP_GET_STATE, b"")
    assert status == b.STATUS_OK and len(state) == 70 * 4
    status, obs = reset(3, state=state)
    assert status == b.STATUS_OK
    back = np.frombuffer(br.handle(b.OP_GET_STATE, b"")[1], "<f4")
    np.testing.assert_allclose(back, np.frombuffer(state, "<f4"), rtol=0, atol=1e-6)
    # Bad input is the adapter's message; anything else a traceback. The bridge lives on.
    status, msg = br.handle(b.OP_STEP, np.zeros(3, "<f4").tobytes())
    assert status == b.STATUS_BAD_INPUT and b"action has 3 components" in msg
    status, msg = br.handle(99, b"")
    assert status == b.STATUS_BAD_INPUT and b"unknown request op 99" in msg
    status, msg = reset(1, options=b'{"env_idx": "bogus"}')
    assert status == b.STATUS_EXCEPTION and msg.startswith(b"Traceback (most recent call last)")
    assert reset(1)[0] == b.STATUS_OK
    br.close()


def test_an_env_registered_by_your_own_module_through_imports():
    """A ManiSkill3 env of the user's own package: made after importing the modules of the run
    config's env.imports, with the registered horizon; without the import it is unknown."""
    import sys
    from pathlib import Path

    from rfcl_sim.adapters import AdapterError, make

    tests = str(Path(__file__).resolve().parent)
    if tests not in sys.path:
        sys.path.insert(0, tests)
    with pytest.raises(AdapterError, match="has no env 'YourPickCube-v1'.*env.imports"):
        make("maniskill3", "YourPickCube-v1")
    adapter = make("maniskill3", "YourPickCube-v1", imports=["ms_user_envs"])
    try:
        assert adapter.horizon == 40
        obs = adapter.reset(3, {})
        state = adapter.get_state()
        adapter.reset(3, {})
        np.testing.assert_allclose(adapter.set_state(state), obs, atol=1e-5)
    finally:
        adapter.close()
