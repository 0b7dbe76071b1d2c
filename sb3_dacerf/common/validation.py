"""The algorithms' exceptions and the checks of their hyper-parameters, action space and temperature, with clear errors."""

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.base_class import maybe_make_env
from stable_baselines3.common.type_aliases import GymEnv


class NonFiniteLossError(RuntimeError, ValueError):
    """A loss became NaN or infinite (nothing was updated); a ``ValueError`` too, so RL Zoo's ``-optimize`` prunes the trial."""


class UnsupportedActionSpaceError(AssertionError, TypeError):
    """An action space a flow or diffusion policy cannot generate: an ``AssertionError`` as SB3 raises, and a ``TypeError``."""


def _is_real(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float, np.number))


@dataclass(frozen=True)
class HyperparameterRule:
    """The valid values of a numeric hyper-parameter: ``is_valid`` of a finite number, and in words (``"in (0, 1]"``)."""

    is_valid: Callable[[Any], bool]
    valid_range: str

    def check(self, name: str, value: Any) -> None:
        """Raise a ``ValueError`` naming ``name``, ``value`` and the valid range unless ``value`` is a valid finite number."""
        finite = _is_real(value) and math.isfinite(value)
        if not finite or not self.is_valid(value):
            finite_number = "a finite number, " if _is_real(value) and not finite else ""
            raise ValueError(f"Invalid {name}={value!r}: it must be {finite_number}{self.valid_range}.")


def integer_at_least(minimum: int, valid_range: str | None = None) -> HyperparameterRule:
    """The rule of a count: an integer ``>= minimum`` (``valid_range`` describes it, ``"an integer >= minimum"`` by default)."""
    return HyperparameterRule(
        lambda value: isinstance(value, (int, np.integer)) and bool(value >= minimum),
        f"an integer >= {minimum}" if valid_range is None else valid_range,
    )


def made_env(env: GymEnv | str | None, algorithm: str, verbose: int) -> GymEnv | None:
    """The environment SB3 makes of ``env`` (``None`` stays ``None``); an error naming ``algorithm`` unless its action
    space is a bounded ``Box``, the only kind a flow or diffusion policy can generate and rescale."""
    if env is None:
        return None
    env = maybe_make_env(env, verbose)
    space = env.action_space
    if not isinstance(space, spaces.Box):
        raise UnsupportedActionSpaceError(
            f"{algorithm} needs a continuous action space (gymnasium.spaces.Box) but the environment has {space}. "
            "Flow and diffusion policies generate real-valued actions: for discrete actions use DQN, PPO or QR-DQN, "
            "or give the environment a Box action space (e.g. highway-env's ContinuousAction)."
        )
    if not (np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high))):
        raise ValueError(
            f"{algorithm} needs a bounded action space to rescale actions to [-1, 1], got low={space.low}, "
            f"high={space.high}. Give the Box finite bounds (e.g. gymnasium.wrappers.ClipAction after setting them)."
        )
    return env


def resolve_target_entropy(target_entropy: Any, auto: float) -> float:
    """The target entropy as a float: ``auto`` for ``"auto"``, else the given finite number (a ``ValueError`` otherwise)."""
    if isinstance(target_entropy, str) and target_entropy == "auto":
        return auto
    if not (_is_real(target_entropy) and math.isfinite(target_entropy)):
        raise ValueError(f"Invalid target_entropy={target_entropy!r}: it must be 'auto' or a finite number (e.g. -dim(A)).")
    return float(target_entropy)


def initial_ent_coef(ent_coef: Any, auto: float, valid_values: str) -> float:
    """The initial ``α`` of SB3's ``ent_coef``: ``auto`` for ``"auto"``, ``x`` for ``"auto_x"`` (``x > 0``), a number
    ``>= 0`` itself (fixed); else a ``ValueError`` ending with ``valid_values``."""
    error = ValueError(f"Invalid ent_coef={ent_coef!r}: it must be {valid_values}")
    if isinstance(ent_coef, str):
        if ent_coef == "auto":
            return auto
        try:
            value = float(ent_coef.removeprefix("auto_")) if ent_coef.startswith("auto_") else math.nan
        except ValueError:
            raise error from None
        if not (math.isfinite(value) and value > 0):
            raise error
        return value
    if not (_is_real(ent_coef) and 0 <= ent_coef < math.inf):
        raise error
    return float(ent_coef)
