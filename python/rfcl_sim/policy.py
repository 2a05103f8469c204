"""A run's exported policy in NumPy alone (docs/POLICY.md): no torch, no rfcl binaries.

``load_policy(RUN_DIR or RUN_DIR/policy.safetensors)`` reads ``policy.safetensors`` and the
``policy.json`` beside it and returns a :class:`Policy`: a deterministic callable from an
observation (``[obs_dim]``, or ``[N, obs_dim]`` for a batch) to the **env action**, the action
rfcl's actors and ``rfcl eval`` send to the env: ``tanh(μ)`` in agent units, divided by
``action_scale`` and clipped to ``[-1, 1]`` when the run rescaled actions (spec 5.7, 6.4).
``Policy.agent_action`` gives ``tanh(μ)`` itself.

The network is the RFCL actor: a ReLU trunk of ``actor_features`` layers, then the mean head
(``y = x @ kernel + bias``, Flax layout), in float32 as in Rust.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

#: The ``format`` of the policy files this loader reads.
FORMAT = "rfcl-actor-v1"


class PolicyError(Exception):
    """A policy file that cannot be used; the message names the file and what was expected."""


def read_safetensors(path: Path) -> dict[str, np.ndarray]:
    """The float32 tensors of a safetensors file (the format's header: 8 bytes of little-endian
    length, then JSON naming each tensor's dtype, shape and byte range)."""
    data = Path(path).read_bytes()
    if len(data) < 8:
        raise PolicyError(f"{path}: too short for a safetensors file")
    (header_len,) = struct.unpack("<Q", data[:8])
    try:
        header = json.loads(data[8:8 + header_len])
    except ValueError as e:
        raise PolicyError(f"{path}: the safetensors header is not JSON ({e})") from e
    header.pop("__metadata__", None)
    body = 8 + header_len
    tensors = {}
    for name, info in header.items():
        if info.get("dtype") != "F32":
            raise PolicyError(f"{path}: tensor {name} is {info.get('dtype')}, expected F32")
        start, end = info["data_offsets"]
        tensors[name] = np.frombuffer(data[body + start:body + end], dtype="<f4").reshape(
            info["shape"]).copy()
    return tensors


class Policy:
    """The deterministic RFCL actor of one export (see the module docs)."""

    def __init__(self, spec: dict, tensors: dict[str, np.ndarray], source: Path) -> None:
        if spec.get("format") != FORMAT:
            raise PolicyError(f"{source}: format {spec.get('format')!r}, expected {FORMAT!r}")
        self.spec = spec
        self.obs_dim, self.action_dim = int(spec["obs_dim"]), int(spec["action_dim"])
        try:
            self.trunk = [(tensors[f"trunk{i}.kernel"], tensors[f"trunk{i}.bias"])
                          for i in range(len(spec["actor_features"]))]
            self.mean = (tensors["mean.kernel"], tensors["mean.bias"])
        except KeyError as e:
            raise PolicyError(f"{source}: no tensor {e} in the policy file") from e
        scale = spec.get("action_scale")
        self.action_scale = None if scale is None else np.asarray(scale, dtype=np.float32)

    def agent_action(self, obs) -> np.ndarray:
        """tanh(μ(obs)), in (-1, 1)."""
        h = np.asarray(obs, dtype=np.float32)
        if h.shape[-1] != self.obs_dim:
            raise PolicyError(f"observation of {h.shape[-1]} values, the policy takes "
                              f"{self.obs_dim}")
        for kernel, bias in self.trunk:
            h = np.maximum(h @ kernel + bias, 0.0)
        return np.tanh(h @ self.mean[0] + self.mean[1]).astype(np.float32)

    def __call__(self, obs) -> np.ndarray:
        """The env action for ``obs``: :meth:`agent_action`, rescaled as the run's actors do."""
        a = self.agent_action(obs)
        if self.action_scale is None:
            return a
        return np.clip(a / self.action_scale, -1.0, 1.0).astype(np.float32)


def load_policy(path) -> Policy:
    """The policy a run exported: ``path`` is its run directory or its ``policy.safetensors``."""
    path = Path(path)
    weights = path / "policy.safetensors" if path.is_dir() else path
    spec_path = weights.with_name("policy.json")
    for p in (weights, spec_path):
        if not p.is_file():
            raise PolicyError(f"{p}: no such file (a run exports its policy when it stops)")
    spec = json.loads(spec_path.read_text())
    return Policy(spec, read_safetensors(weights), weights)
