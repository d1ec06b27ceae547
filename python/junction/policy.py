"""The learner's broadcast policy in PyTorch: a weights blob (safetensors, `common/src/
weights.rs`) rebuilt as the Gaussian policy of `common/src/policy.rs`, observation normaliser
included, acting exactly as the Rust actor does.

The Rust actor's behaviour, reproduced op for op: observations normalised as
`clamp((obs − mean) / sqrt(var + 1e-8), −10, 10)`; the mean action from an MLP with tanh
hidden layers (the Rust tanh itself, `junction._native.tanh_`: `torch.tanh` differs in the
last bit), which with a state-dependent std (`action_std = "state"` in the blob's
metadata) also outputs a log-std offset added to the learned `policy_log_std`; the action
`mean + exp(log_std) · noise` with standard-normal noise, *not*
clipped (the simulator clips what it applies, the fragment ships the action itself); and its
log-probability `Σ −z²/2 − log_std − ln(2π)/2` with `z = (action − mean) / exp(log_std)`,
summed over the two action values, in float32.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass

import numpy as np
import torch

from . import _native

#: The observation layout this package builds observations in (`spec::OBS_LAYOUT_VERSION`).
OBS_LAYOUT_VERSION = 1
OBS_CLIP = 10.0
OBS_VAR_EPS = 1e-8
LCF_MEAN_KEY, LCF_STD_KEY = "lcf_mean_deg", "lcf_std_deg"


class PolicyError(ValueError):
    """A weights blob this package cannot act with."""


@dataclass(frozen=True)
class LcfDistribution:
    """CoPO's LCF distribution N(μ, σ) in degrees, from a blob's metadata: agents draw φ from
    it at spawn and see `(φ/90 + 1)/2` as one more observation value."""

    mean_deg: float
    std_deg: float

    def sample(self, rng: np.random.Generator) -> float:
        return float(np.clip(self.mean_deg + self.std_deg * rng.standard_normal(), -90.0, 90.0))


def read_safetensors(data: bytes) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Tensors (float32) and Junction metadata of a safetensors blob."""
    if len(data) < 8:
        raise PolicyError("not a safetensors blob: shorter than its header length")
    (header_len,) = struct.unpack("<Q", data[:8])
    if header_len > len(data) - 8:
        raise PolicyError("not a safetensors blob: its header runs past the end")
    try:
        header = json.loads(data[8 : 8 + header_len])
    except ValueError as e:
        raise PolicyError(f"not a safetensors blob: {e}") from None
    body = memoryview(data)[8 + header_len :]
    metadata = {}
    tensors = {}
    for name, entry in header.items():
        if name == "__metadata__":
            junction = entry.get("junction") if isinstance(entry, dict) else None
            if junction is not None:
                try:
                    metadata = json.loads(junction)
                except ValueError:
                    raise PolicyError("the blob's junction metadata is not JSON") from None
            continue
        if entry.get("dtype") != "F32":
            raise PolicyError(f"tensor {name!r} is {entry.get('dtype')}, only F32 is supported")
        begin, end = entry["data_offsets"]
        shape = tuple(int(d) for d in entry["shape"])
        if not 0 <= begin <= end <= len(body) or end - begin != 4 * math.prod(shape):
            raise PolicyError(f"tensor {name!r}'s data does not match its shape {shape}")
        values = np.frombuffer(body[begin:end], dtype="<f4").reshape(shape)
        if not np.isfinite(values).all():
            raise PolicyError(f"tensor {name!r} holds a NaN or infinite value")
        tensors[name] = values
    return tensors, metadata


class GaussianPolicy:
    """A broadcast Gaussian policy on the CPU (`torch.no_grad` throughout)."""

    def __init__(self, data: bytes):
        tensors, meta = read_safetensors(data)
        kind = meta.get("policy", "gaussian")
        if kind != "gaussian":
            raise PolicyError(
                f"the blob holds a {kind!r} policy; the Python actors drive Gaussian (PPO) "
                "policies only"
            )
        try:
            self.version = int(meta["version"])
            layout = int(meta["obs_layout_version"])
            self.obs_dim = int(meta["obs_dim"])
            self.action_dim = int(meta["action_dim"])
            hidden = [int(h) for h in meta["hidden"].split(",")]
        except (KeyError, ValueError) as e:
            raise PolicyError(f"the blob's metadata is incomplete or invalid: {e}") from None
        self.state_std = meta.get("action_std", "global") == "state"
        if meta.get("action_std", "global") not in ("global", "state"):
            raise PolicyError(f"the blob's action_std {meta['action_std']!r} is neither global nor state")
        if layout != OBS_LAYOUT_VERSION:
            raise PolicyError(
                f"the policy was trained on observation layout {layout}; this package builds "
                f"layout {OBS_LAYOUT_VERSION}"
            )
        self.lcf = _lcf_distribution(meta)
        t = lambda name: torch.from_numpy(_tensor(tensors, name).copy())  # noqa: E731
        self.layers = []
        width = self.obs_dim
        outputs = 2 * self.action_dim if self.state_std else self.action_dim
        for i, size in enumerate(hidden + [outputs]):
            w, b = t(f"policy.l{i}.weight"), t(f"policy.l{i}.bias")
            if w.shape != (size, width) or b.shape != (size,):
                raise PolicyError(f"layer {i} has shape {tuple(w.shape)}, expected {(size, width)}")
            self.layers.append((w, b))
            width = size
        self.log_std = t("policy_log_std")
        self.mean = t("obs_norm.mean")
        self.var = t("obs_norm.var")
        for name, v, n in [("policy_log_std", self.log_std, self.action_dim),
                           ("obs_norm.mean", self.mean, self.obs_dim),
                           ("obs_norm.var", self.var, self.obs_dim)]:
            if tuple(v.shape) != (n,):
                raise PolicyError(f"{name} has shape {tuple(v.shape)}, expected ({n},)")
        self._std_denominator = torch.sqrt(self.var + OBS_VAR_EPS)
        self._half_ln_2pi = 0.5 * math.log(2.0 * math.pi)

    def _distribution(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean action and log-std of each row."""
        h = torch.clamp((obs - self.mean) / self._std_denominator, -OBS_CLIP, OBS_CLIP)
        last = len(self.layers) - 1
        for i, (w, b) in enumerate(self.layers):
            h = torch.nn.functional.linear(h, w, b)
            if i != last:
                h = h.contiguous()
                _native.tanh_(h.numpy())
        if self.state_std:
            a = self.action_dim
            return h[:, :a], h[:, a:] + self.log_std
        return h, self.log_std.expand_as(h)

    def act(self, obs: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Actions (unclipped) and their log-probabilities for `obs` (rows × obs_dim) and
        standard-normal `noise` (rows × action_dim; zeros give the mean action)."""
        with torch.no_grad():
            o = torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32))
            z_in = torch.from_numpy(np.ascontiguousarray(noise, dtype=np.float32))
            mean, log_std = self._distribution(o)
            actions = mean + log_std.exp() * z_in
            z = (actions - mean) / log_std.exp()
            per_dim = z.square() * -0.5 - log_std - self._half_ln_2pi
            log_probs = per_dim.sum(dim=-1)
        return actions.numpy(), log_probs.numpy()

    def sample(self, obs: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        noise = rng.standard_normal((obs.shape[0], self.action_dim), dtype=np.float32)
        return self.act(obs, noise)

    def deterministic(self, obs: np.ndarray) -> np.ndarray:
        return self.act(obs, np.zeros((obs.shape[0], self.action_dim), np.float32))[0]


def _tensor(tensors: dict[str, np.ndarray], name: str) -> np.ndarray:
    if name not in tensors:
        raise PolicyError(f"tensor {name!r} is missing")
    return tensors[name]


def _lcf_distribution(meta: dict[str, str]) -> LcfDistribution | None:
    mean, std = meta.get(LCF_MEAN_KEY), meta.get(LCF_STD_KEY)
    if mean is None and std is None:
        return None
    try:
        d = LcfDistribution(float(mean), float(std))
    except (TypeError, ValueError):
        raise PolicyError(f"metadata {LCF_MEAN_KEY}/{LCF_STD_KEY} is invalid") from None
    if not (abs(d.mean_deg) <= 90.0 and d.std_deg > 0.0 and math.isfinite(d.std_deg)):
        raise PolicyError(f"metadata {LCF_MEAN_KEY}/{LCF_STD_KEY} is invalid")
    return d


def load_file(path: str) -> GaussianPolicy:
    """A policy from a `policy.safetensors` file."""
    with open(path, "rb") as f:
        return GaussianPolicy(f.read())
