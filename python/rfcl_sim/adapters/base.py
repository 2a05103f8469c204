"""The adapter contract between a Python simulator and rfcl's Rust actor.

An adapter wraps one simulator instance and exposes exactly what the Rust `Env` trait
(actor/src/env.rs) needs. The Rust side owns rewards (+1 per success step), time limits and
curricula; an adapter never terminates an episode on success and never sums rewards.

Every array crossing the boundary is a flat ``float32`` NumPy vector:

* observations: ``obs_dim`` values;
* actions: ``action_dim`` values in ``[-1, 1]``;
* states: ``state_dim`` values, flattened as :meth:`Adapter.state_layout` says (the same layout as
  the ``env_states`` of a demo file, core/src/demo/layout.rs).

Restoring a demo state is always ``reset(seed, options)`` then ``set_state(state)`` (spec 2.4,
12.13): geometry and goals the state vector does not carry come from the seed and options.

**Rendering** (eval videos) is opt-in: an adapter made with the ``render_size`` option (square frames
of that many pixels a side, :func:`check_render_size`) creates its simulator with rendering enabled,
and :meth:`Adapter.render` returns an RGB frame of the current state. Without the option the
simulator is made exactly as if rendering did not exist, and ``render()`` raises
:class:`AdapterError` naming the option.
"""
from __future__ import annotations

import abc
import dataclasses
import importlib
from typing import Any, Callable

import numpy as np

#: The state-entry kinds of core/src/demo/layout.rs (`StateKind`), as strings.
STATE_KINDS = ("flat", "actor", "articulation", "field")

#: The smallest and largest ``render_size`` (pixels a side) an adapter accepts.
RENDER_SIZE_MIN, RENDER_SIZE_MAX = 16, 1024


class AdapterError(Exception):
    """Bad input to an adapter (wrong dims, unknown option, inconsistent state).

    The message names the argument and what was expected; the Rust side shows it verbatim.
    """


@dataclasses.dataclass(frozen=True)
class MakeOptions:
    """The options of ``make`` that every suite takes (the run config's env section), as given: each
    adapter checks the values itself, so that its messages name the suite. A suite's further
    options (ManiSkill's ``sim_backend``, ``imports``, ...) are keyword arguments of its adapter.
    """

    #: The horizon H (default: the suite's, spec 8.3, or the env's registered one).
    max_episode_steps: int | None = None
    #: The controller (``None``: the suite's default; some suites have only that one).
    control_mode: str | None = None
    #: A dict of env constructor arguments, from those the suite allows.
    env_kwargs: dict[str, Any] | None = None
    #: Seeds the RNG that unseeded resets draw their seeds from.
    seed: int | None = None
    #: ``None`` (default: no rendering) or the pixels a side of the square frames of
    #: :meth:`Adapter.render` (:func:`check_render_size`).
    render_size: int | None = None

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The option names, in declaration order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def of(cls, suite: str, env_id: str, kwargs: dict[str, Any]) -> MakeOptions:
        """``make``'s keyword arguments ``kwargs`` as options; names outside :meth:`names` are
        refused by name (rather than with the TypeError the constructor would raise)."""
        unknown = sorted(set(kwargs) - set(cls.names()))
        if unknown:
            raise AdapterError(
                f"{suite}: unknown argument(s) {unknown} for {env_id}; expected some of "
                f"{list(cls.names())}"
            )
        return cls(**kwargs)


class Adapter(abc.ABC):
    """One simulator instance, stepped by one Rust env."""

    #: Suite name as in the run config (`env.suite`): "maniskill3", "metaworld", "adroit".
    suite: str
    #: The simulator's env id, e.g. "PickCube-v1", "pick-place-v3", "AdroitHandDoor-v1".
    env_id: str
    obs_dim: int
    action_dim: int
    #: The task's horizon H (spec 8.3): the Rust actor truncates episodes after H steps.
    horizon: int
    #: The ``render_size`` option the adapter was made with (``None``: it does not render).
    render_size: int | None = None

    @abc.abstractmethod
    def state_layout(self) -> list[tuple[str, str, int]]:
        """``(name, kind, len)`` parts of the state vector, back to back, in order.

        ``kind`` is one of :data:`STATE_KINDS`; ``name`` is the path below ``env_states`` in a demo
        file (``actors/cube``, ``articulations/panda``, ``qpos``).
        """

    @property
    def state_dim(self) -> int:
        return sum(n for _, _, n in self.state_layout())

    @abc.abstractmethod
    def reset(self, seed: int | None, options: dict[str, Any]) -> np.ndarray:
        """Resets to the initial state of ``seed`` (deterministic) or, with ``None``, to one drawn
        from the env's own RNG. Returns the observation."""

    @abc.abstractmethod
    def set_state(self, state: np.ndarray) -> np.ndarray:
        """Sets the flat state (called right after :meth:`reset` with the demo's seed and options)
        and returns the observation of that state. Afterwards :meth:`get_state` returns ``state``
        (up to the simulator's float precision)."""

    @abc.abstractmethod
    def step(self, action: np.ndarray) -> tuple[np.ndarray, bool]:
        """Applies one action; returns the observation after it and whether that state is a success
        state (from the simulator's ``info``). Never terminates."""

    @abc.abstractmethod
    def get_state(self) -> np.ndarray:
        """The current flat state, laid out as :meth:`state_layout` says."""

    def render(self) -> np.ndarray:
        """An RGB frame of the current state (the state after the last reset, ``set_state`` or
        step), seen from the suite's video camera: a C-contiguous ``(H, W, 3)`` ``uint8`` array,
        rows top to bottom, ``H == W == render_size``.

        Only an adapter made with the ``render_size`` option renders; one made without it raises
        :class:`AdapterError` naming the option. Rendering reads the state and never changes it.
        This default is for adapters with no renderer at all: it raises :class:`AdapterError`.
        """
        raise AdapterError(
            f"{self.suite}: the {type(self).__name__} of {self.env_id} has no renderer"
        )

    def close(self) -> None:
        """Releases the simulator."""

    # Helpers for implementations -------------------------------------------------------------

    def _check_action(self, action: np.ndarray) -> np.ndarray:
        a = np.asarray(action, dtype=np.float32).reshape(-1)
        if a.shape[0] != self.action_dim:
            raise AdapterError(
                f"action has {a.shape[0]} components, {self.env_id} takes {self.action_dim}"
            )
        if not np.all(np.isfinite(a)):
            raise AdapterError(f"action {a.tolist()} has a component that is not a finite number")
        return a

    def _check_state(self, state: np.ndarray) -> np.ndarray:
        s = np.asarray(state, dtype=np.float32).reshape(-1)
        if s.shape[0] != self.state_dim:
            raise AdapterError(
                f"state has {s.shape[0]} values, the state layout of {self.env_id} has "
                f"{self.state_dim} ({self.state_layout()})"
            )
        return s

    def _no_render_size(self) -> AdapterError:
        """The error of :meth:`render` on an adapter made without ``render_size``."""
        return AdapterError(
            f"{self.suite}: render() needs the render_size option (e.g. render_size=256, square "
            f"frames of that many pixels), and this {self.env_id} adapter was made without it"
        )

    def _frame(self, image: Any) -> np.ndarray:
        """``image`` (an array or tensor, with or without a leading batch axis of 1) as the
        contiguous ``(H, W, 3)`` ``uint8`` frame :meth:`render` returns."""
        if hasattr(image, "detach"):
            image = image.detach().cpu().numpy()
        f = np.asarray(image)
        if f.ndim == 4 and f.shape[0] == 1:
            f = f[0]
        n = self.render_size
        if f.ndim != 3 or f.shape[2] != 3 or f.dtype != np.uint8 or (
                n is not None and f.shape[:2] != (n, n)):
            raise RuntimeError(
                f"{self.suite}: the renderer of {self.env_id} returned a {f.dtype} array of shape "
                f"{f.shape}, not an ({n}, {n}, 3) uint8 RGB frame"
            )
        return np.ascontiguousarray(f)


def check_render_size(suite: str, render_size: Any) -> int | None:
    """The ``render_size`` option: ``None`` (no renderer, the default) or an integer from
    :data:`RENDER_SIZE_MIN` to :data:`RENDER_SIZE_MAX`, the width and height of the square frames
    :meth:`Adapter.render` returns."""
    if render_size is None:
        return None
    # bool is an int subclass, but True is no size.
    if (isinstance(render_size, bool) or not isinstance(render_size, (int, np.integer))
            or not RENDER_SIZE_MIN <= render_size <= RENDER_SIZE_MAX):
        raise AdapterError(
            f"{suite}: render_size must be null (no rendering) or an integer from "
            f"{RENDER_SIZE_MIN} to {RENDER_SIZE_MAX} (pixels a side), got {render_size!r}"
        )
    return int(render_size)


def import_modules(suite: str, modules: Any) -> None:
    """Imports every module of the config's ``env.imports`` (a list of module names), so that the
    envs they register exist; an import that fails names the module and why."""
    if modules is None:
        return
    if not isinstance(modules, (list, tuple)) or not all(isinstance(m, str) for m in modules):
        raise AdapterError(f"{suite}: imports must be a list of module names, got {modules!r}")
    for module in modules:
        try:
            importlib.import_module(module)
        except Exception as e:  # noqa: BLE001 - any failure of the user's module, by name
            raise AdapterError(
                f"{suite}: env.imports: importing '{module}' failed ({type(e).__name__}: {e})"
            ) from e


def entry_point(what: str, spec: str) -> Callable[..., Any]:
    """``module:callable`` (a dotted name after the colon) as the callable; ``what`` names the
    option in the errors (``gymnasium``, ``--policy``)."""
    module, sep, name = spec.partition(":")
    if not sep or not module or not name:
        raise AdapterError(f"{what}: '{spec}': expected module:callable, e.g. my_package.envs:make")
    try:
        target: Any = importlib.import_module(module)
    except Exception as e:  # noqa: BLE001 - the user's module, by name
        raise AdapterError(
            f"{what}: '{spec}': importing '{module}' failed ({type(e).__name__}: {e})"
        ) from e
    for part in name.split("."):
        if not hasattr(target, part):
            raise AdapterError(f"{what}: '{spec}': '{module}' has no '{name}'")
        target = getattr(target, part)
    if not callable(target):
        raise AdapterError(f"{what}: '{spec}': '{name}' is not callable")
    return target
