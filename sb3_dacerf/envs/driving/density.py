"""
Traffic densities of the driving scenarios, and the distributions an env draws one from at every reset:
``gym.make(env_id, density=...)`` takes ``"sparse"``, ``"normal"`` or ``"dense"`` (every episode), ``"random"`` (the
three alike), a list of densities (drawn alike) or a dict of weights, e.g. ``{"sparse": 1, "normal": 2}`` (drawn in
proportion; densities left out or with weight 0 never are). The draw comes from the env's random generator, so
``reset(seed=s)`` gives the same density every time. This module imports no simulator.
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
    :param density: a density, ``"random"``, a list of densities or a dict of weights >= 0 with a positive sum
    :return: ``{density: probability}`` of the densities that can be drawn, in the order of :data:`DENSITIES`
    :raises ValueError: an unknown or repeated density, an empty list, weights that are negative, not finite or all 0
    :raises TypeError: a value of another type
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
