"""Code the MetaWorld and Adroit adapters share.

Both wrap one gymnasium MuJoCo env, take the common ``make`` options and no others
(:class:`~rfcl_sim.adapters.base.MakeOptions`) and keep their state as named ``field`` entries
(``qpos``, ``qvel``, then the suite's own fields). The checks of those options' values live here
once so that both suites accept and refuse the same input. Every message starts with the suite
name ("adroit: ...", "metaworld: ..."), like the rest of those adapters' messages.
"""
from __future__ import annotations

import atexit
import functools
import os
import weakref
from typing import Any

import numpy as np

from .base import Adapter, AdapterError, check_render_size

#: The env constructor arguments that ``render_size`` sets, so ``env_kwargs`` must not.
RENDER_ENV_KWARGS = ("render_mode", "width", "height")
#: The ``MUJOCO_GL`` an adapter made with ``render_size`` sets when it is unset: EGL renders
#: offscreen without a display, on a GPU (the vendor's libEGL) or, through Mesa's libEGL
#: (libegl1, libegl-mesa0), on the CPU (llvmpipe). OSMesa needs libosmesa6, which set-ups rarely
#: have, and GLFW needs a display.
DEFAULT_MUJOCO_GL = "egl"


def check_env_kwargs(suite: str, env_id: str, env_kwargs: dict[str, Any] | None,
                     allowed: tuple[str, ...]) -> dict[str, Any]:
    """A copy of ``env_kwargs`` (``None`` is empty), refused if it names an argument outside
    ``allowed``: only constructor arguments that leave the task unchanged may pass."""
    env_kwargs = dict(env_kwargs or {})
    bad = sorted(set(env_kwargs) - set(allowed))
    if bad:
        raise AdapterError(
            f"{suite}: env_kwargs {bad} are not supported for {env_id}; expected some of "
            f"{list(allowed)}"
        )
    return env_kwargs


def check_horizon(suite: str, max_episode_steps: Any, default: int) -> int:
    """The horizon H: ``max_episode_steps`` (a positive integer), or ``default`` when it is
    ``None``."""
    if max_episode_steps is None:
        return default
    # bool is an int subclass, but True is no horizon.
    if (isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, (int, np.integer))
            or max_episode_steps < 1):
        raise AdapterError(f"{suite}: max_episode_steps must be a positive integer, got "
                           f"{max_episode_steps!r}")
    return int(max_episode_steps)


def render_env_kwargs(suite: str, env_id: str, env_kwargs: dict[str, Any],
                      render_size: int | None) -> dict[str, Any]:
    """``env_kwargs`` plus what ``render_size`` (already checked) asks of a gymnasium MuJoCo env:
    ``render_mode="rgb_array"`` and a square ``width`` x ``height``. Without ``render_size``,
    ``env_kwargs`` unchanged. (The adapter calls :func:`headless_gl` before it imports the suite.)"""
    if render_size is None:
        return env_kwargs
    clash = sorted(set(RENDER_ENV_KWARGS) & set(env_kwargs))
    if clash:
        raise AdapterError(
            f"{suite}: env_kwargs {clash} cannot be given with render_size for {env_id}: "
            "render_size sets render_mode='rgb_array' and width = height = render_size"
        )
    return {**env_kwargs, "render_mode": "rgb_array", "width": render_size,
            "height": render_size}


def start_rendering(suite: str, render_size: Any) -> int | None:
    """The checked ``render_size`` (:func:`~rfcl_sim.adapters.base.check_render_size`); with one,
    :func:`headless_gl` is set up, so call it before the suite imports MuJoCo."""
    size = check_render_size(suite, render_size)
    if size is not None:
        headless_gl()
    return size


def headless_gl() -> str:
    """Sets ``MUJOCO_GL`` when it is unset (to ``PYOPENGL_PLATFORM`` if that names a headless
    backend, so the two agree, else :data:`DEFAULT_MUJOCO_GL`) and returns it. gymnasium reads it
    when an env creates its GL context (the first ``render()``), MuJoCo when it is imported."""
    platform = os.environ.get("PYOPENGL_PLATFORM", "").lower()
    return os.environ.setdefault(
        "MUJOCO_GL", platform if platform in ("egl", "osmesa") else DEFAULT_MUJOCO_GL)


class FieldAdapter(Adapter):
    """An adapter whose state is the ``field`` entries of ``self._layout``, back to back.

    A subclass's ``__init__`` sets ``_wrapped`` (the env gymnasium made), ``_env`` (the unwrapped
    gymnasium ``MujocoEnv``), ``_layout``, ``_rng`` (the RNG that unseeded resets draw their seeds
    from) and ``render_size``.
    """

    _wrapped: Any
    _env: Any
    _layout: list[tuple[str, str, int]]
    _rng: np.random.Generator
    #: Whether frames are turned by 180 degrees (a camera defined upside down).
    _rotate_frames: bool = False
    #: What closes the GL context at interpreter exit (set by the first render).
    _close_at_exit: Any = None

    def state_layout(self) -> list[tuple[str, str, int]]:
        # A copy, so that a caller cannot change the layout.
        return list(self._layout)

    def render(self) -> np.ndarray:
        """The env's ``rgb_array`` frame (gymnasium's MuJoCo renderer, offscreen, ``MUJOCO_GL``)."""
        if self.render_size is None:
            raise self._no_render_size()
        renderer = self._env.mujoco_renderer
        viewer = renderer._viewers.get("rgb_array")
        if viewer is not None:
            # Each env has its own GL context and gymnasium only switches between the contexts of
            # one env: make ours current, as another adapter in this process may have rendered.
            viewer.make_context_current()
            frame = self._env.render()
        else:
            try:
                frame = self._env.render()
            except Exception as e:  # noqa: BLE001 - the first render creates the GL context
                raise RuntimeError(
                    f"{self.suite}: MuJoCo could not render {self.env_id} offscreen with "
                    f"MUJOCO_GL={os.environ.get('MUJOCO_GL')!r} ({type(e).__name__}: {e}). "
                    "MUJOCO_GL=egl needs libEGL with a GPU driver or Mesa (Debian: libegl1 "
                    "libegl-mesa0); MUJOCO_GL=osmesa needs libosmesa6"
                ) from e
            # An adapter still open at exit frees its GL context before MuJoCo's EGL display is
            # terminated (atexit runs last-registered first), which would otherwise print
            # tracebacks from the context's __del__.
            self._close_at_exit = functools.partial(_close_renderer, weakref.ref(self))
            atexit.register(self._close_at_exit)
        if self._rotate_frames:
            frame = frame[::-1, ::-1]
        return self._frame(frame)

    def close(self) -> None:
        if self._close_at_exit is not None:
            atexit.unregister(self._close_at_exit)
            self._close_at_exit = None
        self._wrapped.close()

    # Helpers for the subclasses -------------------------------------------------------------------

    def _reset_seed(self, seed: int | None) -> int:
        """The seed a reset uses: ``seed``, checked, or with ``None`` a fresh one from ``_rng``."""
        if seed is None:
            return int(self._rng.integers(2**63))
        # bool is an int subclass, but True is no seed.
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise AdapterError(
                f"{self.suite}: reset seed must be a non-negative integer, got {seed!r}")
        return int(seed)

    def _state_fields(self, state: np.ndarray) -> dict[str, np.ndarray]:
        """``state`` (checked against the layout) split into its fields; a field with a value that
        is not a finite number is refused by name, before it reaches the simulator."""
        parts = self._split(self._check_state(state))
        for name, values in parts.items():
            if not np.all(np.isfinite(values)):
                raise AdapterError(
                    f"{self.suite}: state field '{name}' of {self.env_id} has a value that is not "
                    "a finite number"
                )
        return parts

    def _split(self, s: np.ndarray) -> dict[str, np.ndarray]:
        """The flat state ``s`` as ``{field name: its values}``, in layout order."""
        parts, offset = {}, 0
        for name, _, n in self._layout:
            parts[name] = s[offset:offset + n]
            offset += n
        return parts


def _close_renderer(adapter_ref: "weakref.ref[FieldAdapter]") -> None:
    adapter = adapter_ref()
    if adapter is not None:
        try:
            adapter._env.mujoco_renderer.close()
        except Exception:  # noqa: BLE001, S110 - best effort at interpreter exit
            pass
