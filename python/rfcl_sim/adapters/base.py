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
"""
from __future__ import annotations

import abc
from typing import Any

import numpy as np

#: The state-entry kinds of core/src/demo/layout.rs (`StateKind`), as strings.
STATE_KINDS = ("flat", "actor", "articulation", "field")


class AdapterError(Exception):
    """Bad input to an adapter (wrong dims, unknown option, inconsistent state).

    The message names the argument and what was expected; the Rust side shows it verbatim.
    """


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
