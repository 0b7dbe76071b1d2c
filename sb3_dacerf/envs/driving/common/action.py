"""
The paper's incremental action ``[Δa_x, Δδ]``, integrated into the commanded acceleration ``a_x`` and front-wheel
angle ``δ`` of highway-env's kinematic bicycle model; its space is a ``Box`` of the raw increment bounds.
"""

from __future__ import annotations

import math

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.common.action import ContinuousAction


class IncrementalAction(ContinuousAction):
    """
    Continuous action ``[Δa_x, Δδ]``, integrated into the command ``[a_x, δ]`` and clipped every policy step, with the
    bounds of the env's config (``acceleration_increment_range``, ``steering_increment_range``, ``acceleration_range``,
    ``steering_range``).
    """

    def __init__(self, env: AbstractEnv) -> None:
        config = env.config
        super().__init__(env, acceleration_range=config["acceleration_range"], steering_range=config["steering_range"])
        increments = [config["acceleration_increment_range"], config["steering_increment_range"]]
        self.increment_low, self.increment_high = np.array(increments).T
        self.command_low, self.command_high = np.array([config["acceleration_range"], config["steering_range"]]).T
        self.command = np.zeros(2)  # integrated [a_x, δ]
        self.applied_increment = np.zeros(2)  # the increment applied after clipping, for the comfort terms

    def space(self) -> spaces.Box:
        return spaces.Box(self.increment_low.astype(np.float32), self.increment_high.astype(np.float32), dtype=np.float32)

    def command_action(self, desired: np.ndarray) -> np.ndarray:
        """The action that moves the command towards ``desired = [a_x, δ]`` as fast as the increment bounds allow."""
        return np.clip(np.asarray(desired, dtype=np.float64) - self.command, self.increment_low, self.increment_high)

    def check(self, action: np.ndarray) -> np.ndarray:
        """:return: ``step()``'s action as a float64 array of shape (2,) (``act`` clips it), or ``ValueError``"""
        try:
            array = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError) as error:
            raise ValueError(f"The action must be two numbers [Δa_x, Δδ], got {action!r}") from error
        if array.shape != (2,):
            raise ValueError(
                f"The action must have shape (2,) ([Δa_x, Δδ] of one env), got shape {array.shape}: "
                "step a single env with one action (a VecEnv splits a batch of actions per env)"
            )
        if not (math.isfinite(array[0]) and math.isfinite(array[1])):
            raise ValueError(
                f"The action contains NaN or infinite values: {array.tolist()}. The policy's output is not a number "
                "(a diverged training, or an observation with NaN fed to it): check its inputs and losses"
            )
        return array

    def act(self, action: np.ndarray) -> None:
        increment = np.clip(np.asarray(action, dtype=np.float64), self.increment_low, self.increment_high)
        command = np.clip(self.command + increment, self.command_low, self.command_high)
        self.applied_increment = command - self.command
        self.command = command
        self.controlled_vehicle.act({"acceleration": float(command[0]), "steering": float(command[1])})
        self.last_action = action
