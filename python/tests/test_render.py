"""Rendering (the ``render_size`` option, ``Adapter.render``, the bridge's ``OP_RENDER``).

Each suite's tests are skipped when its simulator is not installed. MuJoCo suites render through
``MUJOCO_GL`` (the adapters default it to ``egl``), ManiSkill3 through SAPIEN's Vulkan renderer.
"""
import importlib.util
import json
import struct
import warnings

import numpy as np
import pytest

from rfcl_sim import adapters, bridge
from rfcl_sim.adapters import AdapterError
from rfcl_sim.adapters.base import Adapter, check_render_size

warnings.filterwarnings("ignore", module="gymnasium")
warnings.filterwarnings("ignore", module="gymnasium_robotics")
# MetaWorld's observation box has equal bounds somewhere; gymnasium's env checker says so per make.
pytestmark = pytest.mark.filterwarnings("ignore:.*maximum and minimum values are equal")

#: suite -> (module that must be installed, a task to render).
SUITES = {
    "maniskill3": ("mani_skill", "PickCube-v1"),
    "metaworld": ("metaworld", "pick-place-v3"),
    "adroit": ("gymnasium_robotics", "AdroitHandDoorSparse-v1"),
}
#: Small frames keep the tests quick (a 64 x 64 frame takes milliseconds on the CPU).
SIZE = 64


def installed(suite):
    return importlib.util.find_spec(SUITES[suite][0]) is not None


def need(suite):
    if not installed(suite):
        pytest.skip(f"{SUITES[suite][0]} is not installed")


@pytest.fixture(scope="module")
def made():
    """suite -> (adapter with render_size, adapter without), made on first use."""
    cache = {}

    def get(suite):
        need(suite)
        if suite not in cache:
            env_id = SUITES[suite][1]
            cache[suite] = (adapters.make(suite, env_id, seed=0, render_size=SIZE),
                            adapters.make(suite, env_id, seed=0))
        return cache[suite]

    yield get
    for pair in cache.values():
        for ad in pair:
            ad.close()


def random_actions(ad, n, seed=0):
    return np.random.default_rng(seed).uniform(-1, 1, (n, ad.action_dim)).astype(np.float32)


@pytest.mark.parametrize("suite", SUITES)
def test_a_frame_shows_the_state_and_rendering_leaves_it_alone(made, suite):
    ad, _ = made(suite)
    ad.reset(3, {})
    first = ad.render()
    assert first.shape == (SIZE, SIZE, 3) and first.dtype == np.uint8
    assert first.flags.c_contiguous
    # Not one colour: a scene, not a cleared buffer.
    assert len(np.unique(first.reshape(-1, 3), axis=0)) > 20
    # Rendering reads the state, never changes it, and the same state gives the same frame.
    state = ad.get_state()
    np.testing.assert_array_equal(ad.render(), first)
    np.testing.assert_array_equal(ad.get_state(), state)
    # The robot moves, and so does the picture.
    for a in random_actions(ad, 10):
        ad.step(a)
    moved = ad.render()
    assert moved.shape == first.shape
    assert np.mean(moved != first) > 0.01
    # A restored state renders as it did.
    ad.reset(3, {})
    ad.set_state(state)
    after_restore = ad.render()
    assert np.mean(np.abs(after_restore.astype(int) - first.astype(int)) > 8) < 0.01


@pytest.mark.parametrize("suite", SUITES)
def test_render_size_changes_nothing_else(made, suite):
    rendering, plain = made(suite)
    assert (rendering.obs_dim, rendering.action_dim, rendering.horizon) == (
        plain.obs_dim, plain.action_dim, plain.horizon)
    assert rendering.state_layout() == plain.state_layout()
    assert rendering.render_size == SIZE and plain.render_size is None
    obs = [rendering.reset(5, {}), plain.reset(5, {})]
    np.testing.assert_array_equal(obs[0], obs[1])
    for a in random_actions(plain, 5, seed=1):
        (o1, s1), (o2, s2) = rendering.step(a), plain.step(a)
        np.testing.assert_array_equal(o1, o2)
        assert s1 == s2
    np.testing.assert_array_equal(rendering.get_state(), plain.get_state())


@pytest.mark.parametrize("suite", SUITES)
def test_render_without_render_size_names_the_option(made, suite):
    _, plain = made(suite)
    with pytest.raises(AdapterError, match="render_size"):
        plain.render()


@pytest.mark.parametrize("suite", SUITES)
@pytest.mark.parametrize("bad", [0, -64, 1025, 4096, True, 64.0, "64"])
def test_bad_render_sizes_are_refused_by_name(suite, bad):
    # Checked before the simulator is imported or made: no suite needs to be installed.
    with pytest.raises(AdapterError, match=f"{suite}: render_size must be"):
        adapters.make(suite, SUITES[suite][1], render_size=bad)


def test_render_size_bounds():
    assert check_render_size("x", None) is None
    assert check_render_size("x", 16) == 16 and check_render_size("x", 1024) == 1024
    assert check_render_size("x", np.int64(256)) == 256
    for bad in (15, 1025):
        with pytest.raises(AdapterError, match="render_size"):
            check_render_size("x", bad)


def test_an_adapter_without_a_renderer_says_so():
    class Bare(Adapter):
        suite, env_id, obs_dim, action_dim, horizon = "bare", "Bare-v0", 1, 1, 1

        def state_layout(self):
            return [("qpos", "field", 1)]

        def reset(self, seed, options):
            return np.zeros(1, np.float32)

        set_state = get_state = reset
        step = reset

    with pytest.raises(AdapterError, match="bare: the Bare of Bare-v0 has no renderer"):
        Bare().render()


@pytest.mark.parametrize(
    "suite,env_kwargs",
    [
        ("maniskill3", {"render_mode": "rgb_array"}),
        ("maniskill3", {"human_render_camera_configs": {"width": 32}}),
        ("metaworld", {"width": 32}),
        ("adroit", {"render_mode": "rgb_array"}),
    ],
)
def test_env_kwargs_cannot_fight_render_size(suite, env_kwargs):
    need(suite)
    with pytest.raises(AdapterError, match="render"):
        adapters.make(suite, SUITES[suite][1], render_size=SIZE, env_kwargs=env_kwargs)


def test_metaworld_frames_are_upright_and_cameras_can_be_chosen():
    need("metaworld")
    import mujoco

    ad = adapters.make("metaworld", "pick-place-v3", seed=0, render_size=SIZE)
    top = adapters.make("metaworld", "pick-place-v3", seed=0, render_size=SIZE,
                        env_kwargs={"camera_name": "topview"})
    try:
        env = ad._env
        camera = env.mujoco_renderer.camera_id
        assert mujoco.mj_id2name(env.model, mujoco.mjtObj.mjOBJ_CAMERA, camera) == "corner"
        # The corner camera's up axis (its frame's y column) points down in the world, so its raw
        # frames are upside down and the adapter turns them by 180 degrees.
        assert env.data.cam_xmat[camera].reshape(3, 3)[2, 1] < -0.5
        np.testing.assert_array_equal(ad.render(), env.render()[::-1, ::-1])
        # A camera from env_kwargs is used as it is.
        np.testing.assert_array_equal(top.render(), top._env.render())
        assert not np.array_equal(top.render(), ad.render())
    finally:
        ad.close()
        top.close()


def test_mujoco_envs_in_one_process_keep_their_own_frames():
    for suite in ("metaworld", "adroit"):
        need(suite)
    a = adapters.make("adroit", "AdroitHandPenSparse-v1", seed=0, render_size=SIZE)
    b = adapters.make("metaworld", "stick-pull-v3", seed=0, render_size=SIZE)
    try:
        a.reset(1, {})
        b.reset(1, {})
        fa = a.render()
        fb = b.render()
        # Each adapter renders in its own GL context, whichever rendered last.
        np.testing.assert_array_equal(a.render(), fa)
        np.testing.assert_array_equal(b.render(), fb)
        assert not np.array_equal(fa, fb)
    finally:
        a.close()
        b.close()


def first_installed():
    for suite in ("adroit", "metaworld", "maniskill3"):
        if installed(suite):
            return suite
    pytest.skip("no simulator suite is installed")


def test_the_bridge_answers_op_render_with_a_header_and_rgb_bytes():
    suite = first_installed()
    env_id = SUITES[suite][1]
    br = bridge.Bridge(suite, env_id, json.dumps({"seed": 0, "render_size": 48}))
    plain = bridge.Bridge(suite, env_id, "{}")
    try:
        assert bridge.OP_RENDER == 4
        status, out = br.handle(bridge.OP_RESET, struct.pack("<BQI", 1, 7, 0))
        assert status == bridge.STATUS_OK
        status, out = br.handle(bridge.OP_RENDER, b"")
        assert status == bridge.STATUS_OK
        width, height = struct.unpack_from("<II", out)
        assert (width, height) == (48, 48)
        assert len(out) == 8 + height * width * 3
        pixels = np.frombuffer(out, np.uint8, offset=8).reshape(height, width, 3)
        np.testing.assert_array_equal(pixels, br.adapter.render())
        # Without render_size: the adapter's message naming the option; the bridge lives on.
        status, msg = plain.handle(bridge.OP_RENDER, b"")
        assert status == bridge.STATUS_BAD_INPUT and b"render_size" in msg
        assert plain.handle(bridge.OP_GET_STATE, b"")[0] == bridge.STATUS_OK
    finally:
        br.close()
        plain.close()
    # A bad render_size fails making the bridge with the adapter's message.
    with pytest.raises(AdapterError, match="render_size"):
        bridge.Bridge(suite, env_id, json.dumps({"render_size": 0}))
