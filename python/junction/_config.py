"""Keyword overrides → `learner --set` items, so an environment's scenario is loaded, checked
and refused exactly as the learner's is (same key names, same messages)."""

from __future__ import annotations

import json
import math
from typing import Any, Mapping

from . import _native

ConfigError = _native.ConfigError


def toml_value(value: Any) -> str:
    """A Python value as a TOML value (what `--set key=VALUE` takes)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise ConfigError(
        f"cannot express {value!r} ({type(value).__name__}) as a configuration value: "
        "use a bool, int, float, str or a list of them"
    )


def set_items(overrides: Mapping[str, Any]) -> list[str]:
    """`scenario.KEY=VALUE` items for keyword overrides.

    A keyword names a key of the `[scenario]` section, nested sections joined by `__`
    (`reward__crash=-10` is `--set scenario.reward.crash=-10`); a key with dots is taken as
    `--set` spells it and must start with `scenario.`.
    """
    items = []
    for key, value in overrides.items():
        if "." in key:
            if not key.startswith("scenario."):
                raise ConfigError(
                    f"override {key!r}: an environment takes the [scenario] section's keys only "
                    "(scenario.KEY=VALUE, or KEY / SECTION__KEY as a keyword)"
                )
            path = key
        else:
            path = "scenario." + key.replace("__", ".")
        items.append(f"{path}={toml_value(value)}")
    return items


def load(scenario: str, overrides: Mapping[str, Any]) -> _native.Scenario:
    """A shipped scenario (or scenario file) with keyword overrides, validated."""
    if not isinstance(scenario, str):
        raise ConfigError(
            f"scenario must be a shipped scenario's name or a file path, not {scenario!r}"
        )
    return _native.load_scenario(scenario, set_items(overrides))
