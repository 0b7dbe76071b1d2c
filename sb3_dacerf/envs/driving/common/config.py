"""
Checks of the driving envs' config values by type and range, run by ``configure()`` (so at ``gym.make`` and on
``reset(options={"config": ...})``): a wrong value fails there with a message that names the key, the expected
type / range and the value given, instead of failing (or silently misbehaving) later inside ``step()``.

Every key of an env's ``default_config()`` has a rule (a test checks it): :data:`COMMON_RULES` for the keys of the
paper's task layer and of highway-env, and each scenario's ``CONFIG_RULES`` for its own keys.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable, Sequence
from typing import TypeGuard

Rule = Callable[[object], str | None]
"""A check of one value: ``None`` if valid, else what was expected (e.g. ``"a number > 0"``)."""


def _is_number(value: object) -> TypeGuard[float]:
    """A real number that is not a ``bool`` (typed as ``float``, which every ``numbers.Real`` compares like)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_integer(value: object) -> TypeGuard[int]:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def number(low: float | None = None, high: float | None = None, *, low_open: bool = False, integer: bool = False) -> Rule:
    """A number (an integer if ``integer``) within ``[low, high]`` (``(low, high]`` if ``low_open``)."""
    kind = "an integer" if integer else "a number"
    bounds = []
    if low is not None:
        bounds.append(f"{'>' if low_open else '>='} {low:g}")
    if high is not None:
        bounds.append(f"<= {high:g}")
    expected = f"{kind} {' and '.join(bounds)}".strip()

    def check(value: object) -> str | None:
        if not _is_number(value) or (integer and not _is_integer(value)):
            return expected
        if value != value:  # NaN
            return expected
        if low is not None and (value <= low if low_open else value < low):
            return expected
        if high is not None and value > high:
            return expected
        return None

    return check


def interval(low: float | None = None, high: float | None = None, *, contains_zero: bool = False) -> Rule:
    """A pair ``[lo, hi]`` of numbers with ``lo <= hi`` within ``[low, high]`` (containing 0 if ``contains_zero``)."""
    within = f" within [{low:g}, {high:g}]" if low is not None and high is not None else ""
    expected = f"a pair [low, high] of numbers with low <= {'0 <= ' if contains_zero else ''}high{within}"

    def check(value: object) -> str | None:
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 2:
            return expected
        lo, hi = value
        if not (_is_number(lo) and _is_number(hi)) or not lo <= hi:
            return expected
        if (low is not None and lo < low) or (high is not None and hi > high):
            return expected
        if contains_zero and not lo <= 0 <= hi:
            return expected
        return None

    return check


def pair(low_open: float = 0.0) -> Rule:
    """A pair of numbers, each > ``low_open``."""
    expected = f"a pair [a, b] of numbers > {low_open:g}"

    def check(value: object) -> str | None:
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 2:
            return expected
        if not all(_is_number(v) and v > low_open for v in value):
            return expected
        return None

    return check


def boolean(allow_none: bool = False) -> Rule:
    expected = "True or False" + (" (or None)" if allow_none else "")

    def check(value: object) -> str | None:
        if value is None and allow_none:
            return None
        return None if value is True or value is False else expected

    return check


def choice(values: Sequence[object]) -> Rule:
    expected = f"one of {list(values)}"
    return lambda value: None if isinstance(value, str) and value in values else expected


#: The traffic vehicle classes ``other_vehicles_type`` may name: highway-env's driver models, never an arbitrary
#: import path (a config read from a file must not import modules)
VEHICLE_CLASSES = tuple(
    f"highway_env.vehicle.behavior.{name}" for name in ("IDMVehicle", "LinearVehicle", "AggressiveVehicle", "DefensiveVehicle")
)


def severe_penalty(value: object) -> str | None:
    """``"dynamic"`` or a number >= 0."""
    if value == "dynamic" or (_is_number(value) and value == value and value >= 0):
        return None
    return "'dynamic' or a number >= 0 (the paper's constant is 200)"


COMMON_RULES: dict[str, Rule] = {
    # highway-env's simulation and rendering keys
    "simulation_frequency": number(0, low_open=True, integer=True),
    "policy_frequency": number(0, low_open=True, integer=True),
    "other_vehicles_type": choice(VEHICLE_CLASSES),
    "screen_width": number(0, low_open=True, integer=True),
    "screen_height": number(0, low_open=True, integer=True),
    "centering_position": interval(0.0, 1.0),
    "scaling": number(0, low_open=True),
    "show_trajectories": boolean(),
    "render_agent": boolean(),
    "offscreen_rendering": boolean(allow_none=True),
    "manual_control": boolean(),
    "real_time_rendering": boolean(),
    "neighbour_vehicles_connected_lanes": boolean(),
    # the paper's task layer
    "duration": number(0, low_open=True),
    "perception_distance": number(0, low_open=True),
    "surrounding_vehicles": number(0, integer=True),
    "reference_waypoints": number(1, integer=True),
    "reference_waypoint_interval": number(0, low_open=True),
    "position_scale": number(0, low_open=True),
    "speed_scale": number(0, low_open=True),
    "acceleration_increment_range": interval(contains_zero=True),
    "steering_increment_range": interval(contains_zero=True),
    "acceleration_range": interval(contains_zero=True),
    "steering_range": interval(-1.5, 1.5, contains_zero=True),  # [rad] the bicycle model needs |δ| < π/2
    "huber_delta": number(0, low_open=True),
    "safe_time_headway": number(0, low_open=True),
    "reference_speed_follows_traffic": boolean(),
    "safe_space_margin": pair(0.0),
    "boundary_threshold": number(0),
    "collision_penalty": severe_penalty,
    "dynamic_penalty_base": number(0),
    "dynamic_penalty_cost_rate": number(0),
    "dynamic_penalty_discount": number(0, 1, low_open=True),
    "stall_timeout": number(0),
    "stall_distance": number(0, low_open=True),
    **{
        key: number(0)
        for key in (
            "rho_lat",
            "rho_long",
            "rho_heading",
            "rho_acc",
            "rho_steer",
            "rho_yaw",
            "rho_jerk",
            "rho_steer_rate",
            "rho_step",
            "rho_front",
            "rho_side",
            "rho_space",
            "rho_rear",
            "rho_boundary",
        )
    },
}


def check_config(config: dict, rules: dict[str, Rule], defaults: dict, env_name: str) -> None:
    """
    Check every value of a config against its rule, and the frequencies against each other.

    :param config: the full config (defaults merged with the overrides)
    :param rules: a rule per key
    :param defaults: the default config, quoted in the messages
    :param env_name: the env's class name, for the messages
    :raises ValueError: a value of the wrong type or out of range, naming the key, what it must be and the value given
    """
    for key, value in config.items():
        rule = rules.get(key)
        expected = rule(value) if rule is not None else None
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
