"""The paper's task layer over a highway-env environment: config, step loop, termination, info and rendering."""

from __future__ import annotations

import os
from collections import deque
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from gymnasium import logger, spaces
from gymnasium.error import ResetNeeded
from highway_env.envs.common.graphics import EnvViewer

from sb3_dacerf.envs.driving.common.action import IncrementalAction
from sb3_dacerf.envs.driving.common.config import COMMON_RULES, Rule, check_config
from sb3_dacerf.envs.driving.common.observation import EgoFrameObservation, Scene, observe_scene
from sb3_dacerf.envs.driving.common.reference import ReferencePath
from sb3_dacerf.envs.driving.common.reward import REWARD_TERMS, REWARD_WEIGHTS, reward_terms
from sb3_dacerf.envs.driving.density import DensitySpec, density_weights

if TYPE_CHECKING:  # what the mixin is mixed into, for the type checkers
    from highway_env.envs.common.abstract import AbstractEnv as _HighwayEnv
else:
    _HighwayEnv = object

# highway-env keys that our action / observation / reward replace: dropped, so that setting one is an error.
_REPLACED_STOCK_KEYS = (
    "observation action collision_reward right_lane_reward high_speed_reward lane_change_reward arrived_reward "
    "reward_speed_range normalize_reward offroad_terminal vehicles_density ego_spacing initial_lane_id "
    "controlled_vehicles destination"
).split()


class PaperDrivingMixin(_HighwayEnv):
    """
    The paper's task layer, first in the bases of a subclass of a highway-env environment, which builds
    ``self.reference`` and ``self.reference_speed`` with the ego and implements ``_road_clearance`` and ``_is_success``.

    :param config: overrides of ``default_config()``; unknown keys and invalid values raise ``ValueError``
    :param render_mode: ``None``, ``"rgb_array"`` or ``"human"``
    :param density: a density or a distribution of them (:mod:`sb3_dacerf.envs.driving.density`)
    """

    DENSITY_CONFIGS: ClassVar[dict[str, dict]] = {}  #: config overrides of each traffic density
    CONFIG_RULES: ClassVar[dict[str, Rule]] = {}  #: type and range checks of the scenario's own config keys
    EVALUATION_CONFIG: ClassVar[dict] = {}  #: the config under which evaluations run (over the trained config)
    reference: ReferencePath
    reference_speed: float
    REFERENCE_ACCELERATION = 0.7  #: [m/s²] the fastest the reference speed rises (the ego accelerates at 0.8 at most)
    reference_speed_ceiling: float  #: [m/s] the last step's reference speed raised by ``REFERENCE_ACCELERATION``
    scene: Scene
    density: str  # of the current episode
    density_weights: dict[str, float]  # the probability of each density an episode can have
    _progress: deque[float]
    observation_space: spaces.Space | None
    action_space: spaces.Space | None
    viewer: EnvViewer | None

    def __init__(self, config: dict | None = None, render_mode: str | None = None, density: DensitySpec = "normal") -> None:
        self.density_weights = density_weights(density)
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"Unknown render_mode {render_mode!r}: expected None or one of {self.metadata['render_modes']}")
        if config is not None and not isinstance(config, dict):
            raise TypeError(f"config must be a dict of overrides, got {type(config).__name__}")
        self.density = next(iter(self.density_weights))
        self._check_density_keys(config or {})
        # With several densities, each reset sets the drawn density's keys.
        density_config = self.DENSITY_CONFIGS[self.density] if len(self.density_weights) == 1 else {}
        super().__init__({**density_config, **(config or {})}, render_mode=render_mode)

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        for key in _REPLACED_STOCK_KEYS:
            config.pop(key, None)
        config.update(
            {
                "simulation_frequency": 10,  # [Hz] one physics step per action: the paper's Δt = 0.1 s
                "policy_frequency": 10,  # [Hz]
                "duration": 30,  # [s]
                "perception_distance": 80.0,  # [m]
                "surrounding_vehicles": 8,  # M
                "reference_waypoints": 10,  # W
                "reference_waypoint_interval": 0.5,  # [s] of travel at the target speed between waypoints
                "position_scale": 50.0,  # [m] observation divisor of positions
                "speed_scale": 30.0,  # [m/s] observation divisor of speeds
                "acceleration_increment_range": [-0.4, 0.25],  # [m/s²] per step
                "steering_increment_range": [-0.025, 0.025],  # [rad] per step
                "acceleration_range": [-0.8, 0.8],  # [m/s²]
                "steering_range": [-0.571, 0.571],  # [rad]
                "huber_delta": 1.0,
                **{f"rho_{name}": weight for name, weight in REWARD_WEIGHTS.items()},
                "safe_time_headway": 1.0,  # Δt_safe [s]
                "safe_space_margin": [3.0, 1.0],  # [m] longitudinal, lateral clearance around the ego body
                "boundary_threshold": 0.5,  # d_thresh [m]
                "collision_penalty": "dynamic",  # of severe events: "dynamic" (see _severe_penalty) or a number
                "dynamic_penalty_base": 200.0,  # the dynamic penalty's floor, at the time limit
                "dynamic_penalty_cost_rate": 20.0,  # per step left: the per-step cost of driving on still preferred
                "dynamic_penalty_discount": 1.0,  # discount of the steps left (the learner's gamma; 1: undiscounted)
                # Less than stall_distance [m] of progress along the reference in stall_timeout [s] (0: never) ends
                # the episode with the severe-event penalty
                "stall_timeout": 0.0,
                "stall_distance": 2.0,
            }
        )
        return config

    def configure(self, config: dict | None) -> None:
        unknown = sorted(set(config or {}) - set(self.default_config()))
        if unknown:
            raise ValueError(
                f"Unknown config key(s) {unknown} for {type(self).__name__}; valid keys: {sorted(self.default_config())}"
            )
        self._check_density_keys(config or {})
        super().configure(config)
        check_config(self.config, self.config_rules(), self.default_config(), type(self).__name__)

    def _check_density_keys(self, config: dict) -> None:
        """Refuse config values for the keys a drawn density sets (the next reset would overwrite them)."""
        if len(getattr(self, "density_weights", ())) < 2:
            return
        density_keys = sorted({key for overrides in self.DENSITY_CONFIGS.values() for key in overrides} & set(config))
        if density_keys:
            raise ValueError(
                f"{type(self).__name__}: config {density_keys} is what each episode's density sets, and this env draws "
                f"the density per episode (probabilities {self.density_weights}): leave {density_keys} out of the "
                "config, or make the env with one density"
            )

    @classmethod
    def config_rules(cls) -> dict[str, Rule]:
        """The type and range check of every config key."""
        return {**COMMON_RULES, **cls.CONFIG_RULES}

    def define_spaces(self) -> None:
        self.observation_type, self.action_type = EgoFrameObservation(self), IncrementalAction(self)
        # The steering command starts at the ego's (non-zero for an exploring start inside a turn).
        if self.controlled_vehicles:
            self.action_type.command[1] = self.controlled_vehicles[0].action["steering"]
        # highway-env rebuilds the spaces on every reset; keeping ours keeps any seed set on them.
        if self.observation_space is None or self.observation_space.shape != self.observation_type.space().shape:
            self.observation_space = self.observation_type.space()
        if self.action_space is None or self.action_space != self.action_type.space():
            self.action_space = self.action_type.space()

    def _reset(self) -> None:
        self._reward_terms = dict.fromkeys(REWARD_TERMS, 0.0)
        self._episode_over = self._warned_step_after_end = False  # terminated or truncated returned, and warned of
        if len(self.density_weights) > 1:
            # From the env's generator, which reset(seed=...) seeds: a seed gives the same density every time.
            names, probabilities = list(self.density_weights), list(self.density_weights.values())
            self.density = names[int(self.np_random.choice(len(names), p=probabilities))]
            self.config.update(self.DENSITY_CONFIGS[self.density])
        super()._reset()
        self.vehicle.MIN_SPEED = 0.0  # the ego stops instead of reversing
        self.reference_speed_ceiling = np.inf
        self.scene = observe_scene(self)
        # the ego's progress along its reference over the last stall_timeout seconds
        window = round(self.config["stall_timeout"] * self.config["policy_frequency"])
        self._progress = deque([self.scene.reference_progress], maxlen=window + 1 if window else None)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """
        Apply ``[Δa_x, Δδ]`` (clipped to the action space), simulate one policy period, then perceive the scene once.

        :raises ValueError: an action of another shape, or with NaN / infinite values
        """
        if self.road is None or self.vehicle is None:
            raise ResetNeeded("Cannot call step() before reset(): call env.reset(seed=...) first")
        action = self.action_type.check(action)
        if self._episode_over and not self._warned_step_after_end:
            logger.warn(  # as Gymnasium's own envs do: warn once, then keep simulating
                "You are calling 'step()' even though this environment has already returned terminated = True or "
                "truncated = True. You should always call 'reset()' once you receive either: the episode is over "
                "(collision, off the road, arrived or time limit) and any further steps are undefined behavior."
            )
            self._warned_step_after_end = True
        self.time += 1 / self.config["policy_frequency"]
        self._simulate(action)
        self.reference_speed_ceiling = self.scene.reference_speed + self.REFERENCE_ACCELERATION / self.config["policy_frequency"]
        self.scene = observe_scene(self)
        self._progress.append(self.scene.reference_progress)
        obs = self.observation_type.observe(self.scene)
        self._reward_terms = self._rewards()
        reward = float(sum(self._reward_terms.values()))
        terminated, truncated = self._is_terminated(), self._is_truncated()
        info = self._info(obs, action)
        if self.render_mode == "human":
            self.render()
        self._episode_over = self._episode_over or terminated or truncated
        return obs, reward, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        if self.viewer is None and self.render_mode is not None:
            # Without a display, pygame initialises SDL's offscreen video driver (the environment is restored after)
            headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") or "SDL_VIDEODRIVER" in os.environ)
            if headless:
                os.environ["SDL_VIDEODRIVER"] = "offscreen"
            try:
                self.viewer = EnvViewer(self)
            finally:
                if headless:
                    os.environ.pop("SDL_VIDEODRIVER", None)
            if self.config["offscreen_rendering"]:
                self.viewer.enabled = True  # highway-env's viewer draws nothing under SDL's "dummy" driver otherwise
        return super().render()

    def _is_truncated(self) -> bool:
        return self.time >= self.config["duration"] - 1e-6  # time accumulates steps of 1 / policy_frequency

    def _start_speed(self) -> float:
        """Initial ego speed [m/s]: ``self.reference_speed`` ± 0.5 m/s (normal noise), never negative."""
        return max(self.reference_speed + self.np_random.normal(0.0, 0.5), 0.0)

    def reference_speed_cap(self) -> float:
        """The highest reference speed [m/s] the scenario allows in its current state: none (``inf``) by default."""
        return np.inf

    def _road_clearance(self, position: np.ndarray) -> float:  # [m] to the nearest road edge, negative off the road
        raise NotImplementedError

    def _is_success(self) -> bool:  # whether the episode's task is achieved
        raise NotImplementedError

    def _severe_penalty(self) -> float:
        """
        The (positive) penalty of a severe event at the current step: ``collision_penalty``, or if ``"dynamic"``,
        ``dynamic_penalty_base + (rho_step + dynamic_penalty_cost_rate) * steps_left`` (the policy steps left, or with
        a ``dynamic_penalty_discount`` γ < 1 their discounted count ``(1 - γ^steps_left) / (1 - γ)``): ending the
        episode is then worse, by at least the base, than driving on at any reward above ``-dynamic_penalty_cost_rate``.
        """
        config = self.config
        if config["collision_penalty"] != "dynamic":
            return float(config["collision_penalty"])
        steps_left = max(round((config["duration"] - self.time) * config["policy_frequency"]), 0)
        discount = config["dynamic_penalty_discount"]
        horizon = steps_left if discount == 1 else (1 - discount**steps_left) / (1 - discount)
        return float(config["dynamic_penalty_base"] + (config["rho_step"] + config["dynamic_penalty_cost_rate"]) * horizon)

    def _rewards(self) -> dict[str, float]:
        """The paper's signed reward and cost terms of the current scene (see :mod:`.reward`)."""
        applied = self.action_type.applied_increment
        return reward_terms(self.config, self.scene, self.vehicle, applied, self._severe_penalty(), self._stalled())

    def _reward(self, action: np.ndarray) -> float:
        return float(sum(self._rewards().values()))

    def _stalled(self) -> bool:
        """Less than ``stall_distance`` of progress in the last ``stall_timeout`` s, without a collision or leaving the road."""
        progress = self._progress
        return (
            progress.maxlen is not None
            and len(progress) == progress.maxlen
            and progress[-1] - progress[0] < self.config["stall_distance"]
            and not (self.vehicle.crashed or self.scene.road_clearance < 0)
        )

    def _is_terminated(self) -> bool:
        return bool(self.vehicle.crashed or self.scene.road_clearance < 0 or self._stalled())

    def _info(self, obs: np.ndarray, action: np.ndarray | None = None) -> dict:
        scene = self.scene
        crashed, off_road, stalled = bool(self.vehicle.crashed), bool(scene.road_clearance < 0), self._stalled()
        return {
            "speed": float(self.vehicle.speed),
            "reference_speed": float(scene.reference_speed),
            "target_speed": float(self.reference_speed),
            "lateral_error": float(scene.lateral_error),
            "crashed": crashed,
            "collision": crashed,
            "off_road": off_road,
            "stalled": stalled,
            "density": self.density,
            "is_success": bool(self._is_success() and not (crashed or off_road or stalled)),
            "reward_terms": dict(self._reward_terms),
        }
