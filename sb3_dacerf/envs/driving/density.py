"""
Traffic densities of the driving scenarios: ``gym.make(env_id, density=...)`` takes ``"sparse"``, ``"normal"`` or
``"dense"``, or a distribution each reset draws the episode's density from with the env's generator: ``"random"``,
a list of densities (drawn alike) or a dict of weights, e.g. ``{"sparse": 1, "normal": 2}``. Imports no simulator.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from typing import TypeAlias

DENSITIES = ("sparse", "normal", "dense")
"""The traffic densities of every driving scenario, from the fewest vehicles to the most."""

DensitySpec: TypeAlias = str | Sequence[str] | Mapping[str, float]
"""A density, ``"random"``, a list of densities or a dict of weights (see the module docstring)."""

_FORMS = (
    f"one of {', '.join(map(repr, DENSITIES))}, 'random' (each episode draws one of them), a list of them "
    "(each episode draws one, e.g. ['sparse', 'normal']) or a dict of weights (e.g. {'sparse': 1, 'dense': 2})"
)


def density_weights(density: object) -> dict[str, float]:
    """
    :return: ``{density: probability}`` of the densities a ``density`` spec draws, in the order of :data:`DENSITIES`
    :raises ValueError: an unknown or repeated density, an empty list, weights negative, not finite or all 0
    """
    if isinstance(density, str):
        if density == "random":
            return dict.fromkeys(DENSITIES, 1.0 / len(DENSITIES))
        if density not in DENSITIES:
            raise ValueError(f"Unknown density {density!r}: expected {_FORMS}")
        return {density: 1.0}
    if isinstance(density, Mapping):
        weights = dict(density)
    elif isinstance(density, Sequence) and not isinstance(density, bytes):
        if not density:
            raise ValueError(f"density=[] lists no density: expected {_FORMS}")
        repeated = sorted({name for name in density if list(density).count(name) > 1}, key=str)
        if repeated:
            raise ValueError(
                f"density={list(density)!r} lists {', '.join(map(repr, repeated))} more than once: list each density "
                "once, or give unequal chances with a dict of weights, e.g. {'sparse': 2, 'normal': 1}"
            )
        weights = dict.fromkeys(density, 1.0)
    else:
        raise TypeError(
            f"density must be a string, a list or a dict, got {density!r} ({type(density).__name__}): expected {_FORMS}"
        )
    unknown = [name for name in weights if name not in DENSITIES]
    if unknown:
        raise ValueError(f"Unknown density {unknown[0]!r} in density={density!r}: expected {_FORMS}")
    for name, weight in weights.items():
        if not isinstance(weight, numbers.Real) or isinstance(weight, bool) or not math.isfinite(weight) or weight < 0:
            raise ValueError(f"density={density!r}: the weight of {name!r} must be a finite number >= 0, got {weight!r}")
    total = sum(weights.values())
    if total <= 0:
        raise ValueError(f"density={density!r}: the weights sum to 0, so no density can be drawn: give one a weight > 0")
    return {name: float(weights[name]) / total for name in DENSITIES if weights.get(name, 0) > 0}
