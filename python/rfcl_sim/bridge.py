"""The Python end of the Rust bridge (actor/src/python/): one adapter behind one byte-level call.

The Rust side sends requests as ``(op, payload)`` and gets ``(status, payload)`` back, the same
frames whether it embeds Python in its own process or drives a ``rfcl-sim-worker`` process over a
pipe; this module is the one place that decodes them on the Python side. All numbers are
little-endian; vectors are packed ``float32``.

Requests:

* ``OP_HELLO`` (empty): the adapter's description as JSON (``suite``, ``env_id``, ``obs_dim``,
  ``action_dim``, ``horizon``, ``state_layout`` as ``[name, kind, len]`` triples, ``python``).
* ``OP_RESET``: ``u8 has_seed, u64 seed, u32 n, n bytes of options JSON, f32 state...``. Resets
  with the seed and options, then, when a state follows, sets it (spec 2.4, 12.13). Answers the
  observation.
* ``OP_STEP``: ``f32 action...``. Answers ``u8 success, f32 obs...``.
* ``OP_GET_STATE`` (empty): answers the flat state.
* ``OP_RENDER`` (empty): answers ``u32 width, u32 height``, then ``height * width * 3`` bytes of
  RGB (``uint8``, row-major, top row first: pixel ``(row, col)`` channel ``c`` is byte
  ``8 + (row * width + col) * 3 + c``), a frame of the current state (:meth:`Adapter.render`).
  Only adapters made with the ``render_size`` option render (``width == height == render_size``);
  otherwise the answer is ``STATUS_BAD_INPUT`` naming the option.

Statuses: ``STATUS_OK``; ``STATUS_BAD_INPUT`` (an :class:`AdapterError`: the message, verbatim);
``STATUS_EXCEPTION`` (any other exception: its formatted traceback). A request never raises out of
:meth:`Bridge.handle`, so one bad call does not take the worker down.
"""
from __future__ import annotations

import json
import struct
import sys
import traceback
from typing import Any

import numpy as np

from . import adapters
from .adapters.base import AdapterError

OP_HELLO, OP_RESET, OP_STEP, OP_GET_STATE, OP_RENDER = 0, 1, 2, 3, 4
STATUS_OK, STATUS_BAD_INPUT, STATUS_EXCEPTION = 0, 1, 2

_RESET_HEAD = struct.Struct("<BQI")
#: The head of an ``OP_RENDER`` answer: width, height.
_FRAME_HEAD = struct.Struct("<II")


class Bridge:
    """One adapter, made from the run config's env options (``kwargs_json``: a JSON object, e.g.
    ``{"max_episode_steps": 50, "render_size": 256}``; ``render_size`` enables ``OP_RENDER``)."""

    def __init__(self, suite: str, env_id: str, kwargs_json: str = "{}") -> None:
        kwargs = json.loads(kwargs_json or "{}")
        if not isinstance(kwargs, dict):
            raise AdapterError(f"adapter options must be a JSON object, got {kwargs_json!r}")
        self.adapter = adapters.make(suite, env_id, **kwargs)

    def hello(self) -> bytes:
        a = self.adapter
        return json.dumps(
            {
                "suite": a.suite,
                "env_id": a.env_id,
                "obs_dim": int(a.obs_dim),
                "action_dim": int(a.action_dim),
                "horizon": int(a.horizon),
                "state_layout": [[n, k, int(l)] for n, k, l in a.state_layout()],
                "python": sys.version.split()[0],
            }
        ).encode()

    def handle(self, op: int, payload: bytes) -> tuple[int, bytes]:
        try:
            return STATUS_OK, self._dispatch(op, payload)
        except AdapterError as e:
            return STATUS_BAD_INPUT, str(e).encode()
        except Exception:  # noqa: BLE001 - every failure goes back to Rust with its traceback
            return STATUS_EXCEPTION, traceback.format_exc().encode()

    def _dispatch(self, op: int, payload: bytes) -> bytes:
        a = self.adapter
        if op == OP_STEP:
            obs, success = a.step(np.frombuffer(payload, dtype="<f4"))
            return bytes([1 if success else 0]) + _pack(obs)
        if op == OP_RESET:
            has_seed, seed, n = _RESET_HEAD.unpack_from(payload)
            head = _RESET_HEAD.size
            options: Any = json.loads(payload[head : head + n] or b"{}")
            if options is None:
                options = {}
            if not isinstance(options, dict):
                raise AdapterError(f"reset options must be a JSON object, got {options!r}")
            obs = a.reset(seed if has_seed else None, options)
            state = np.frombuffer(payload[head + n :], dtype="<f4")
            if state.size:
                obs = a.set_state(state)
            return _pack(obs)
        if op == OP_GET_STATE:
            return _pack(a.get_state())
        if op == OP_RENDER:
            return _pack_frame(a.render())
        if op == OP_HELLO:
            return self.hello()
        raise AdapterError(f"unknown request op {op}")

    def close(self) -> None:
        self.adapter.close()


def _pack(v: np.ndarray) -> bytes:
    return np.ascontiguousarray(v, dtype="<f4").tobytes()


def _pack_frame(frame: np.ndarray) -> bytes:
    """An ``OP_RENDER`` answer: the frame's width and height, then its RGB bytes, top row first."""
    f = np.asarray(frame)
    if f.ndim != 3 or f.shape[2] != 3 or f.dtype != np.uint8:
        raise ValueError(f"render() returned a {f.dtype} array of shape {f.shape}, not an "
                         "(H, W, 3) uint8 RGB frame")
    height, width = f.shape[:2]
    return _FRAME_HEAD.pack(width, height) + np.ascontiguousarray(f).tobytes()
