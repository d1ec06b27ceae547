"""CoPO's published curves and table (`copo_reference.json`, its source cited there): the
reference every training curve here is read against."""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

PATH = Path(__file__).with_name("copo_reference.json")


@lru_cache(maxsize=1)
def reference() -> dict:
    return json.loads(PATH.read_text())


def reference_scene(scene: str) -> str:
    """The scene whose reference `scene` is read against: CoPO's intersection for Junction's
    twin of it and for MetaDrive's own (`same_scene`), else the scene itself."""
    return reference().get("same_scene", {}).get(scene, scene)


def curve(scene: str, method: str = "ippo") -> dict[int, float]:
    """{environment steps: success} of CoPO's curve of `method` on `scene` ({} if none)."""
    points = reference()["curves"].get(reference_scene(scene), {}).get(method, {})
    return {int(k): v for k, v in points.items()}


def curve_by_agent_steps(scene: str, method: str = "ippo") -> dict[int, float]:
    """The same at agent-steps (environment steps × the scene's agent-steps per step), for
    the scenes where that ratio is known (the intersection's ≈ 25); {} for the others."""
    ratio = reference()["agent_steps_per_env_step"].get(reference_scene(scene))
    if not isinstance(ratio, (int, float)):
        return {}
    return {k * ratio: v for k, v in curve(scene, method).items()}


def table(scene: str) -> dict[str, float]:
    """CoPO's reported success per method on `scene` (best smoothed training window)."""
    return dict(reference()["table"].get(reference_scene(scene), {}))

