"""Simulator adapters (see :mod:`rfcl_sim.adapters.base` for the contract).

``make(suite, env_id, **kwargs)`` is the one entry point the Rust bridge calls. Each suite's module
is imported lazily, so a machine without one simulator can still run the others.
"""
from __future__ import annotations

import importlib
from typing import Any

from .base import Adapter, AdapterError, STATE_KINDS, check_render_size

#: suite name (config `env.suite`) -> module in this package with a ``make(env_id, **kwargs)``.
SUITES = {
    "maniskill3": "maniskill",
    "metaworld": "metaworld",
    "adroit": "adroit",
    "gymnasium": "gym_envs",
}


def make(suite: str, env_id: str, **kwargs: Any) -> Adapter:
    """A new adapter for ``env_id`` of ``suite``. ``kwargs`` are the run config's env options
    (``control_mode``, ``max_episode_steps``, ``env_kwargs``, ``render_size``, ...), which each suite
    documents. Every suite takes ``render_size`` (``None``, the default, or 16 to 1024): only with
    it does the adapter render (:meth:`Adapter.render`, square RGB frames of that size)."""
    if suite not in SUITES:
        raise AdapterError(
            f"unknown suite '{suite}': expected one of {sorted(SUITES)} (pointmaze is native Rust)"
        )
    module = importlib.import_module(f".{SUITES[suite]}", __name__)
    return module.make(env_id, **kwargs)


__all__ = ["Adapter", "AdapterError", "STATE_KINDS", "SUITES", "check_render_size", "make"]
