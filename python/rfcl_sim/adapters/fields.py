"""Code the MetaWorld and Adroit adapters share.

Both wrap one gymnasium MuJoCo env, take the same :func:`make` options and keep their state as
named ``field`` entries (``qpos``, ``qvel``, then the suite's own fields). The checks live here
once so that both suites accept and refuse the same input. Every message starts with the suite
name ("adroit: ...", "metaworld: ..."), like the rest of those adapters' messages.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import Adapter, AdapterError

#: Keyword arguments the suites' ``make`` accepts (the run config's env section).
MAKE_KWARGS = ("max_episode_steps", "control_mode", "env_kwargs", "seed")


def check_make_kwargs(suite: str, env_id: str, kwargs: dict[str, Any]) -> None:
    """Refuses keyword arguments outside :data:`MAKE_KWARGS`, naming them (rather than the
    TypeError the adapter's constructor would raise)."""
    unknown = sorted(set(kwargs) - set(MAKE_KWARGS))
    if unknown:
        raise AdapterError(
            f"{suite}: unknown argument(s) {unknown} for {env_id}; expected some of "
            f"{list(MAKE_KWARGS)}"
        )


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


class FieldAdapter(Adapter):
    """An adapter whose state is the ``field`` entries of ``self._layout``, back to back.

    A subclass's ``__init__`` sets ``_wrapped`` (the env gymnasium made), ``_layout`` and ``_rng``
    (the RNG that unseeded resets draw their seeds from).
    """

    _wrapped: Any
    _layout: list[tuple[str, str, int]]
    _rng: np.random.Generator

    def state_layout(self) -> list[tuple[str, str, int]]:
        # A copy, so that a caller cannot change the layout.
        return list(self._layout)

    def close(self) -> None:
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
