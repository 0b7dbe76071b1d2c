"""
Type and range checks of the driving envs' config values, run by ``configure()``: every key of an env's
``default_config()`` has a rule, in :data:`COMMON_RULES` or the scenario's ``CONFIG_RULES``.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable, Sequence
from typing import TypeGuard

Rule = Callable[[object], str | None]
"""A check of one value: ``None`` if valid, else what was expected (e.g. ``"a number > 0"``)."""


def _is_number(value: object) -> TypeGuard[float]:
    """A real number that is not a ``bool``."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_pair(value: object) -> TypeGuard[Sequence[float]]:
    return not isinstance(value, (str, bytes)) and isinstance(value, Sequence) and len(value) == 2 and all(map(_is_number, value))


def number(low: float | None = None, high: float | None = None, *, low_open: bool = False, integer: bool = False) -> Rule:
    """A number (an integer if ``integer``) within ``[low, high]`` (``(low, high]`` if ``low_open``), not NaN."""
    bounds = [f"{'>' if low_open else '>='} {low:g}"] if low is not None else []
    bounds += [f"<= {high:g}"] if high is not None else []
    expected = f"{'an integer' if integer else 'a number'} {' and '.join(bounds)}".strip()

    def check(value: object) -> str | None:
        if not _is_number(value) or (integer and not isinstance(value, numbers.Integral)) or value != value:
            return expected
        above = low is None or (value > low if low_open else value >= low)
        return None if above and (high is None or value <= high) else expected

    return check


def interval(low: float | None = None, high: float | None = None, *, contains_zero: bool = False) -> Rule:
    """A pair ``[lo, hi]`` of numbers with ``lo <= hi`` within ``[low, high]`` (containing 0 if ``contains_zero``)."""
    within = f" within [{low:g}, {high:g}]" if low is not None and high is not None else ""
    expected = f"a pair [low, high] of numbers with low <= {'0 <= ' if contains_zero else ''}high{within}"

    def check(value: object) -> str | None:
        if not _is_pair(value) or not value[0] <= value[1]:
            return expected
        lo, hi = value
        valid = (low is None or lo >= low) and (high is None or hi <= high) and (not contains_zero or lo <= 0 <= hi)
        return None if valid else expected

    return check


def positive_pair(value: object) -> str | None:
    return None if _is_pair(value) and all(v > 0 for v in value) else "a pair [a, b] of numbers > 0"


def boolean(allow_none: bool = False) -> Rule:
    expected = "True or False" + (" (or None)" if allow_none else "")
    return lambda value: None if value is True or value is False or (allow_none and value is None) else expected


def choice(values: Sequence[object]) -> Rule:
    expected = f"one of {list(values)}"
    return lambda value: None if isinstance(value, str) and value in values else expected


def severe_penalty(value: object) -> str | None:
    """``"dynamic"`` or a number >= 0."""
    if value == "dynamic" or (_is_number(value) and value >= 0):
        return None
    return "'dynamic' or a number >= 0 (the paper's constant is 200)"


#: The traffic vehicle classes ``other_vehicles_type`` may name: highway-env's driver models (a config read from a file
#: must not import arbitrary modules)
VEHICLE_CLASSES = tuple(
    f"highway_env.vehicle.behavior.{name}" for name in ("IDMVehicle", "LinearVehicle", "AggressiveVehicle", "DefensiveVehicle")
)
COMMON_RULES: dict[str, Rule] = {
    # highway-env's simulation and rendering keys, then the paper's task layer
    **dict.fromkeys(
        ["simulation_frequency", "policy_frequency", "screen_width", "screen_height"], number(0, low_open=True, integer=True)
    ),
    "other_vehicles_type": choice(VEHICLE_CLASSES),
    "centering_position": interval(0.0, 1.0),
    "offscreen_rendering": boolean(allow_none=True),
    **dict.fromkeys(
        "show_trajectories render_agent manual_control real_time_rendering neighbour_vehicles_connected_lanes".split(),
        boolean(),
    ),
    **dict.fromkeys(
        "scaling duration perception_distance reference_waypoint_interval position_scale speed_scale huber_delta "
        "safe_time_headway stall_distance".split(),
        number(0, low_open=True),
    ),
    **dict.fromkeys(
        "boundary_threshold dynamic_penalty_base dynamic_penalty_cost_rate stall_timeout rho_lat rho_long rho_heading "
        "rho_acc rho_steer rho_yaw rho_jerk rho_steer_rate rho_step rho_front rho_side rho_space rho_rear rho_boundary".split(),
        number(0),
    ),
    "surrounding_vehicles": number(0, integer=True),
    "reference_waypoints": number(1, integer=True),
    **dict.fromkeys(
        ["acceleration_increment_range", "steering_increment_range", "acceleration_range"], interval(contains_zero=True)
    ),
    "steering_range": interval(-1.5, 1.5, contains_zero=True),  # [rad] the bicycle model needs |δ| < π/2
    "safe_space_margin": positive_pair,
    "collision_penalty": severe_penalty,
    "dynamic_penalty_discount": number(0, 1, low_open=True),
}


def check_config(config: dict, rules: dict[str, Rule], defaults: dict, env_name: str) -> None:
    """
    Check every value of a full config against its rule, and the frequencies against each other: ``ValueError`` names
    the env, the key, what it must be, the value given and the default.
    """
    for key, value in config.items():
        expected = rules[key](value) if key in rules else None
        if expected is not None:
            raise ValueError(
                f"{env_name} config[{key!r}] must be {expected}, got {value!r} ({type(value).__name__}): "
                f"give such a value, or leave the key out for its default {defaults.get(key)!r}"
            )
    simulation, policy = config["simulation_frequency"], config["policy_frequency"]
    if simulation % policy:
        raise ValueError(
            f"{env_name} config['simulation_frequency'] ({simulation} Hz) must be a multiple of config['policy_frequency'] "
            f"({policy} Hz): each action lasts a whole number of physics steps (the paper's setting is 10 and 10)"
        )
