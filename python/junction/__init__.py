"""Junction's traffic simulator for Python.

- `parallel_env(scenario, seed, **overrides)`: one scene as a PettingZoo `ParallelEnv`.
- `vector_env(scenario, num_scenes, seed, **overrides)`: the fast path, every agent slot of N
  scenes as NumPy arrays.
- Gymnasium: `gymnasium.make("Junction-Intersection-v0")`, one learning car among human drivers.

Overrides are the `[scenario]` keys of the run configuration (`learner config --defaults`),
nested sections joined by `__` (`reward__crash=-10.0`) or written as `--set` writes them
(`**{"scenario.reward.crash": -10.0}`); they are checked exactly as `learner --set` checks
them and refused with `ConfigError` (a `ValueError`). docs/PYTHON.md has the details.

- `junction.analysis`: progress curves, CoPO's smoothing, intervals and tables of finished runs
  (standard library only: it imports without the native module, so scripts run it from a
  checkout before `make python`).
- `junction.ledger`: the reconciliation of a run's fragment ledgers (docs/FAULTS.md; standard
  library only, like `junction.analysis`).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from . import _native
    from ._config import ConfigError
    from .parallel import ParallelEnv
    from .vector import OUTCOMES, VectorEnv

__all__ = [
    "ConfigError",
    "OUTCOMES",
    "ParallelEnv",
    "SHIPPED_SCENARIOS",
    "VectorEnv",
    "load_scenario",
    "parallel_env",
    "vector_env",
]

# The environments need the native module (`make python`); they load on first use, so that
# `junction.analysis` imports from a plain checkout.
_LAZY = {
    "ConfigError": ("._config", "ConfigError"),
    "ParallelEnv": (".parallel", "ParallelEnv"),
    "OUTCOMES": (".vector", "OUTCOMES"),
    "VectorEnv": (".vector", "VectorEnv"),
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        module, attribute = _LAZY[name]
        return getattr(importlib.import_module(module, __name__), attribute)
    if name == "SHIPPED_SCENARIOS":
        # Names `scenario=` accepts besides a scenario file's path.
        from . import _native

        return tuple(_native.SHIPPED_SCENARIOS)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def parallel_env(scenario: str = "intersection", seed: int = 0, **overrides: Any) -> ParallelEnv:
    """One scene of `scenario` as a PettingZoo `ParallelEnv` (`render_mode="rgb_array"` to
    draw it)."""
    from .parallel import ParallelEnv

    return ParallelEnv(scenario, seed, **overrides)


def vector_env(
    scenario: str = "intersection", num_scenes: int = 1, seed: int = 0, **overrides: Any
) -> VectorEnv:
    """`num_scenes` scenes of `scenario`, every agent slot as NumPy arrays."""
    from .vector import VectorEnv

    return VectorEnv(scenario, num_scenes, seed, **overrides)


def load_scenario(scenario: str = "intersection", **overrides: Any) -> _native.Scenario:
    """The validated scenario an environment would run (name, slots, obs_dim, TOML)."""
    from . import _config

    return _config.load(scenario, overrides)


def _register_gymnasium() -> None:
    """One learning car among the intersection's human drivers: 9 of them (humans.share = 0.9
    of the vehicles), MetaDrive's 4-way geometry. Skipped where gymnasium is not installed
    (the analysis needs none of it)."""
    try:
        import gymnasium
    except ImportError:
        return
    gymnasium.register(
        id="Junction-Intersection-v0",
        entry_point="junction.gym_env:SingleAgentEnv",
        kwargs={"scenario": "intersection", "humans__share": 0.9},
    )


_register_gymnasium()
