"""
The paper's incremental action on highway-env's kinematic bicycle model.

``[Δa_x, Δδ]`` with ``Δa_x ∈ [-0.4, 0.25]`` m/s² and ``Δδ ∈ [-0.025, 0.025]`` rad per policy step (0.1 s, i.e. jerk in
[-4, 2.5] m/s³ and steering rate within ±0.25 rad/s). The increments are integrated into the commanded longitudinal
acceleration ``a_x ∈ [-0.8, 0.8]`` m/s² and front-wheel steering angle ``δ ∈ [-0.571, 0.571]`` rad, which are exactly
the ``acceleration`` (m/s²) and ``steering`` (front-wheel angle, rad) inputs of highway-env's kinematic bicycle model
(``highway_env.vehicle.kinematics.Vehicle``). Both start at 0 on ``reset()`` (an exploring start of the intersection,
``reference_start_probability``, starts δ at the steering of the path's curvature). The ego cannot reverse.

With a steering feedforward (the env's ``steering_feedforward`` config key; ``steering_feedforward`` set before each
``act``), ``Δδ`` integrates a steering *residual* instead, and δ moves towards ``residual + feedforward`` (the
nominal steering of the path ahead) at most by the steering-rate bounds per step: a zero action then follows the
path's curvature, and the policy learns the corrections.

With ``normalized=True`` (the env's ``normalized_action`` config key) the action space is ``Box(-1, 1, (2,))`` and an
action component ``u`` is the increment ``u · high`` for ``u ≥ 0`` and ``u · |low|`` for ``u < 0``: the same bounds,
with the zero increment at the centre of the box. With the raw bounds the centre is ``Δa_x = -0.075`` m/s² per step
(``[-0.4, 0.25]`` is not symmetric), so a policy whose output sits at the centre of its box, as SB3's policies do
before they learn, brakes to a standstill.

With ``mode="target"`` (the env's ``action_mode`` config key) the action is no longer the increment but the command it
moves towards: ``Box(-1, 1, (2,))`` scaled to the command bounds on each side of zero (``a_x ∈ [-0.8, 0.8]`` m/s²,
``δ ∈ [-0.571, 0.571]`` rad, or the steering residual on top of the feedforward), and each step the command moves
towards it by at most the increment bounds. The physical limits (jerk, steering rate) and the comfort terms are the
same; what changes is that noise on the action is not integrated: an exploring policy's noise jitters the command
around its target, where with increments it adds up to a random walk of the steering and the acceleration.
"""

from __future__ import annotations

import math

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.common.action import ContinuousAction


def from_unit(unit: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """``u`` in ``[-1, 1]`` to ``u · high`` for ``u >= 0`` and ``u · |low|`` for ``u < 0`` (zero stays zero)."""
    return np.where(unit >= 0, unit * high, -unit * low)


def to_unit(value: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The inverse of :func:`from_unit` for ``low <= value <= high`` (a bound of 0 on one side is never divided by)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(value >= 0, value / high, value / -low)


class IncrementalAction(ContinuousAction):
    """
    Continuous action ``[Δa_x, Δδ]``: increments of the commanded acceleration [m/s²] and front-wheel
    steering angle [rad] of highway-env's kinematic bicycle model, integrated and clipped every policy step.

    The action space is a ``Box`` with the raw increment bounds (SB3 rescales Box bounds itself).

    :param env: the environment
    :param acceleration_increment_range: bounds of Δa_x per policy step [m/s²]
    :param steering_increment_range: bounds of Δδ per policy step [rad]
    :param acceleration_range: bounds of the integrated a_x [m/s²]
    :param steering_range: bounds of the integrated δ [rad]
    :param normalized: actions in ``[-1, 1]``, scaled to the increment bounds on each side of zero
    :param mode: ``"increment"`` (the paper's: the action is ``[Δa_x, Δδ]``) or ``"target"`` (the action, in
        ``[-1, 1]`` scaled to the command bounds on each side of zero, is the command ``[a_x, δ]`` to move towards
        within the increment bounds; with a feedforward its steering is the residual on top of it)
    """

    MODES = ("increment", "target")

    # Class-level defaults: an action type pickled before these existed (a training checkpoint's env) still acts.
    normalized = False
    mode = "increment"
    steering_feedforward: float | None = None
    steering_residual = 0.0

    def __init__(
        self,
        env: AbstractEnv,
        acceleration_increment_range: tuple[float, float] = (-0.4, 0.25),
        steering_increment_range: tuple[float, float] = (-0.025, 0.025),
        acceleration_range: tuple[float, float] = (-0.8, 0.8),
        steering_range: tuple[float, float] = (-0.571, 0.571),
        normalized: bool = False,
        mode: str = "increment",
        **kwargs,
    ) -> None:
        if mode not in self.MODES:
            raise ValueError(f"mode must be one of {list(self.MODES)}, got {mode!r}")
        super().__init__(env, acceleration_range=acceleration_range, steering_range=steering_range)
        self.increment_low = np.array([acceleration_increment_range[0], steering_increment_range[0]])
        self.increment_high = np.array([acceleration_increment_range[1], steering_increment_range[1]])
        self.command_low = np.array([acceleration_range[0], steering_range[0]])
        self.command_high = np.array([acceleration_range[1], steering_range[1]])
        self.normalized = normalized
        self.mode = mode
        self.command = np.zeros(2)  # integrated [a_x, δ]
        self.applied_increment = np.zeros(2)  # increment actually applied after clipping, for the comfort terms
        self.steering_feedforward: float | None = None
        """Nominal steering [rad] of the path ahead for the next ``act``; ``None``: no feedforward (the paper's action)."""
        self.steering_residual = 0.0
        """With a feedforward: the integrated ``Δδ``, which δ follows on top of the feedforward [rad]."""

    def space(self) -> spaces.Box:
        if self.normalized or self.mode == "target":
            return spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        return spaces.Box(self.increment_low.astype(np.float32), self.increment_high.astype(np.float32), dtype=np.float32)

    def to_increment(self, action: np.ndarray) -> np.ndarray:
        """The increments ``[Δa_x, Δδ]`` an action asks for, clipped to their bounds (``mode="increment"``)."""
        action = np.asarray(action, dtype=np.float64)
        if self.normalized:
            return from_unit(np.clip(action, -1.0, 1.0), self.increment_low, self.increment_high)
        return np.clip(action, self.increment_low, self.increment_high)

    def to_action(self, increment: np.ndarray) -> np.ndarray:
        """The action that asks for the increments ``[Δa_x, Δδ]`` (clipped to their bounds); inverse of ``to_increment``."""
        increment = np.clip(np.asarray(increment, dtype=np.float64), self.increment_low, self.increment_high)
        if self.normalized:
            return to_unit(increment, self.increment_low, self.increment_high)
        return increment

    def to_target(self, action: np.ndarray) -> np.ndarray:
        """The command ``[a_x, δ]`` (δ: the residual, with a feedforward) an action asks for (``mode="target"``)."""
        return from_unit(np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0), self.command_low, self.command_high)

    def command_action(self, desired: np.ndarray, feedforward: float | None = None) -> np.ndarray:
        """
        The action that moves the command towards ``desired = [a_x, δ]`` (the steering applied, feedforward included)
        as fast as the increment bounds allow, in either mode: what a controller that computes the command it wants
        (:class:`sb3_dacerf.envs.driving.scripted.ScriptedDriver`) gives the env.

        :param desired: the command wanted
        :param feedforward: the steering feedforward of the coming step (the env's ``_steering_feedforward()``),
            with the env's ``steering_feedforward`` on; ``None`` without
        """
        desired = np.array(desired, dtype=np.float64)
        if self.mode == "target":
            desired = np.clip(desired, self.command_low, self.command_high)
            if feedforward is not None:
                desired[1] -= feedforward
            return np.clip(to_unit(desired, self.command_low, self.command_high), -1, 1)
        increment = desired - self.command
        if feedforward is not None:
            # Δδ moves the residual on top of the feedforward: aim the sum at the steering wanted.
            increment[1] = desired[1] - feedforward - self.steering_residual
        return self.to_action(increment)

    def check(self, action: np.ndarray) -> np.ndarray:
        """
        Check that an action is one finite ``[Δa_x, Δδ]`` pair (values beyond the bounds are allowed: ``act`` clips them).

        :param action: the action given to ``step()``
        :return: the action as a float64 array of shape (2,)
        :raises ValueError: wrong shape, non-numeric or non-finite values
        """
        try:
            array = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError) as error:
            raise ValueError(f"The action must be two numbers [Δa_x, Δδ], got {action!r}") from error
        if array.shape != (2,):
            raise ValueError(
                f"The action must have shape (2,) ([Δa_x, Δδ] of one env), got shape {array.shape}: "
                "step a single env with one action (a VecEnv splits a batch of actions per env)"
            )
        if not (math.isfinite(array[0]) and math.isfinite(array[1])):  # scalar math: a third of np.isfinite's cost
            raise ValueError(
                f"The action contains NaN or infinite values: {array.tolist()}. The policy's output is not a number "
                "(a diverged training, or an observation with NaN fed to it): check its inputs and losses"
            )
        return array

    def act(self, action: np.ndarray) -> None:
        if self.mode == "target":
            wanted = self.to_target(action)
            if self.steering_feedforward is not None:
                self.steering_residual = float(wanted[1])
                wanted[1] += self.steering_feedforward
            wanted = np.clip(wanted, self.command_low, self.command_high)
            command = self.command + np.clip(wanted - self.command, self.increment_low, self.increment_high)
            self._apply(action, command)
            return
        increment = self.to_increment(action)
        command = np.clip(self.command + increment, self.command_low, self.command_high)
        if self.steering_feedforward is not None:
            low, high = self.command_low[1], self.command_high[1]
            self.steering_residual = min(max(self.steering_residual + increment[1], low), high)
            target = min(max(self.steering_residual + self.steering_feedforward, low), high)
            # The steering-rate bounds hold for the steering actually applied, feedforward included.
            command[1] = self.command[1] + min(max(target - self.command[1], self.increment_low[1]), self.increment_high[1])
        self._apply(action, command)

    def _apply(self, action: np.ndarray, command: np.ndarray) -> None:
        self.applied_increment = command - self.command
        self.command = command
        self.controlled_vehicle.act({"acceleration": float(command[0]), "steering": float(command[1])})
        self.last_action = action
