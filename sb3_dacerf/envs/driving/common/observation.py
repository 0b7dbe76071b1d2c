"""
What the ego perceives (:class:`Scene`, computed once per step) and the paper's flat ego-frame observation of it.

Observation (flat ``float32`` vector, ego frame: x along the ego heading, y along highway-env's lateral axis, i.e. to
the driver's right on the rendered image, where world y points down)

- ego, 5 values: ``[v_x / speed_scale, v_y / speed_scale, r, a_x, δ]``; body-frame velocity of the bicycle model (m/s),
  yaw rate ``r`` (rad/s), commanded ``a_x`` (m/s²) and ``δ`` (rad) unscaled;
- reference, 4 × W values (W = ``reference_waypoints``, default 10): ``[x / position_scale, y / position_scale, cos φ,
  sin φ]`` for waypoints at the ego's projection on the reference path and then every ``reference_waypoint_interval``
  (0.5 s) of travel at the target speed, so the spacing encodes the target speed; φ is the path heading relative to
  the ego heading;
- surrounding vehicles, 6 × M values (M = ``surrounding_vehicles``, default 8), nearest first, within
  ``perception_distance``: ``[x / position_scale, y / position_scale, cos φ, sin φ, v / speed_scale, mask]``, relative
  position of the vehicle centre, relative heading, absolute speed, mask 1; padding rows are all zeros (mask 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from gymnasium import spaces
from highway_env import utils
from highway_env.envs.common.observation import ObservationType

from sb3_dacerf.envs.driving.common.reference import ReferencePath

EGO_FEATURES = 5
WAYPOINT_FEATURES = 4
VEHICLE_FEATURES = 6


def vehicle_rows(config: dict) -> tuple[int, int, int]:
    """
    Where the surrounding vehicles are in the flat observation of an env with this config: the ``rows`` of
    :class:`sb3_dacerf.common.vec_normalize.MaskedVecNormalize`.

    :param config: the env's config (``reference_waypoints``, ``surrounding_vehicles``)
    :return: the index of the first vehicle entry, the number of vehicle rows (M) and their length (6, the mask last)
    """
    return EGO_FEATURES + WAYPOINT_FEATURES * config["reference_waypoints"], config["surrounding_vehicles"], VEHICLE_FEATURES


class PerceivingEnv(Protocol):
    """
    What :func:`observe_scene` and :class:`EgoFrameObservation` read of an env: the paper's driving envs
    (:class:`~sb3_dacerf.envs.driving.common.abstract.PaperDrivingMixin`) provide it. Reading it through this protocol
    keeps the observation independent of the task layer that uses it.
    """

    config: dict
    """The env's config (``perception_distance``, ``reference_waypoints``, the scales, ...)."""
    reference: ReferencePath
    """The ego's reference path."""
    reference_speed: float
    """The episode's target speed [m/s]."""

    def reference_speed_cap(self) -> float:
        """The highest reference speed [m/s] the scenario allows in its current state (``inf``: the target speed)."""
        ...

    @property
    def vehicle(self) -> Any:
        """The ego vehicle (highway-env's)."""

    @property
    def road(self) -> Any:
        """The road with every vehicle (highway-env's)."""

    @property
    def action_type(self) -> Any:
        """The ego's action type, whose ``command`` is the applied ``[a_x, δ]``."""

    def _road_clearance(self, position: np.ndarray) -> float:
        """Distance [m] from a position to the nearest road edge, negative off the road."""


@dataclass
class Scene:
    """What the ego perceives at one step, in SI units and in the ego frame."""

    ego: np.ndarray
    """[v_x, v_y, r, a_x, δ]"""
    waypoints: np.ndarray
    """(W, 4) reference waypoints [x, y, cos φ, sin φ]"""
    vehicles: np.ndarray
    """(K, 7) vehicles within perception distance, nearest first: [x, y, cos φ, sin φ, v, length, width]"""
    lateral_error: float
    heading_error: float
    reference_curvature: float
    road_clearance: float
    """Distance from the ego centre to the road edge [m], negative off the road."""
    reference_progress: float = 0.0
    """Arc length of the ego's projection on its reference path [m]."""
    reference_speed: float = 0.0
    """The speed [m/s] the waypoints are spaced by and the speed-tracking term asks for at this step: the episode's
    target speed, or with ``reference_speed_follows_traffic`` the lower speed the vehicle ahead allows."""


def vehicle_gaps(vehicles: np.ndarray, ego_length: float, ego_width: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Clearances between the ego's body and each scene vehicle's, along and across the ego's heading.

    :param vehicles: the scene's vehicles, ego frame, ``[x, y, cos φ, sin φ, v, length, width]`` rows
    :param ego_length: the ego's length [m]
    :param ego_width: the ego's width [m]
    :return: the longitudinal and lateral gaps [m] (negative: the bodies overlap along that axis), and the mask of
        the vehicles in the ego's corridor ahead (in front of its centre and overlapping it laterally)
    """
    x, y = vehicles[:, 0], vehicles[:, 1]
    gap_long = np.abs(x) - (ego_length + vehicles[:, 5]) / 2
    gap_lat = np.abs(y) - (ego_width + vehicles[:, 6]) / 2
    return gap_long, gap_lat, (x > 0) & (gap_lat < 0)


def traffic_following_speed(
    target_speed: float,
    vehicles: np.ndarray,
    ego_length: float,
    ego_width: float,
    deceleration: float,
    time_headway: float,
) -> float:
    """
    The target speed capped by what the nearest vehicle ahead in the ego's corridor allows.

    The cap is the highest speed from which braking at ``deceleration`` still closes on that vehicle's speed before
    the gap shrinks to its ``time_headway`` distance: ``v_lead + sqrt(2 b max(gap - v_lead Δt_safe, 0))``. It equals
    the lead vehicle's speed at the safe-following distance and rises with the gap, so a learner rewarded for
    tracking it starts braking early enough for the paper's limited deceleration (0.8 m/s²: 9 m/s of closing speed
    take 50 m). Vehicles beyond the perception distance leave the target speed as it is.

    :param target_speed: the episode's target speed [m/s]
    :param vehicles: the scene's vehicles, ego frame, ``[x, y, cos φ, sin φ, v, length, width]`` rows
    :param ego_length: the ego's length [m]
    :param ego_width: the ego's width [m]
    :param deceleration: the braking the cap assumes, > 0 [m/s²]
    :param time_headway: the following distance the cap keeps, in seconds of the lead vehicle's speed [s]
    :return: the reference speed [m/s], at most ``target_speed`` and never negative
    """
    if not len(vehicles):
        return target_speed
    gap_long, _, ahead = vehicle_gaps(vehicles, ego_length, ego_width)
    if not ahead.any():
        return target_speed
    gaps = gap_long[ahead]
    lead_speeds = np.maximum(vehicles[ahead, 4] * vehicles[ahead, 2], 0.0)
    caps = lead_speeds + np.sqrt(2 * deceleration * np.maximum(gaps - lead_speeds * time_headway, 0.0))
    return float(min(target_speed, caps.min()))


def observe_scene(env: PerceivingEnv) -> Scene:
    """
    Compute what the ego perceives in the env's current state (reads the env, changes nothing).

    :param env: a paper driving env after ``reset()``
    :return: the scene, for the observation, the reward, the termination and the info
    """
    config = env.config
    ego = env.vehicle
    beta = math.atan(0.5 * math.tan(ego.action["steering"]))
    ego_state = np.array(
        [
            ego.speed * math.cos(beta),
            ego.speed * math.sin(beta),
            ego.speed * math.sin(beta) / (ego.LENGTH / 2),  # heading rate of the bicycle model
            *env.action_type.command,
        ]
    )
    cos_h, sin_h = math.cos(ego.heading), math.sin(ego.heading)
    to_ego_frame_t = np.array([[cos_h, -sin_h], [sin_h, cos_h]])

    vehicles = np.zeros((0, 7))
    others = [v for v in env.road.vehicles if v is not ego]
    if others:
        # One array of [x, y, heading, speed, length, width] per vehicle, then vectorised (indexing the position
        # is twice as fast as unpacking it).
        data = np.array([(v.position[0], v.position[1], v.heading, v.speed, v.LENGTH, v.WIDTH) for v in others])
        data[:, :2] -= ego.position
        distances = np.hypot(data[:, 0], data[:, 1])
        visible = np.flatnonzero(distances < config["perception_distance"])
        data = data[visible[np.argsort(distances[visible], kind="stable")]]
        relative = data[:, 2] - ego.heading
        vehicles = np.empty((len(data), 7))
        vehicles[:, :2] = data[:, :2] @ to_ego_frame_t
        vehicles[:, 2], vehicles[:, 3], vehicles[:, 4:] = np.cos(relative), np.sin(relative), data[:, 3:]

    s, lateral = env.reference.project(ego.position)
    reference_speed = min(env.reference_speed, env.reference_speed_cap())
    if config["reference_speed_follows_traffic"]:
        reference_speed = traffic_following_speed(
            reference_speed, vehicles, ego.LENGTH, ego.WIDTH, -config["acceleration_range"][0], config["safe_time_headway"]
        )
    step = reference_speed * config["reference_waypoint_interval"]
    points, headings, curvatures = env.reference.at(s + step * np.arange(config["reference_waypoints"]))
    relative_headings = headings - ego.heading
    waypoints = np.empty((len(points), WAYPOINT_FEATURES))
    waypoints[:, :2] = (points - ego.position) @ to_ego_frame_t
    waypoints[:, 2], waypoints[:, 3] = np.cos(relative_headings), np.sin(relative_headings)

    return Scene(
        ego=ego_state,
        waypoints=waypoints,
        vehicles=vehicles,
        lateral_error=lateral,
        heading_error=float(utils.wrap_to_pi(ego.heading - float(headings[0]))),
        reference_curvature=float(curvatures[0]),
        road_clearance=env._road_clearance(ego.position),
        reference_progress=s,
        reference_speed=reference_speed,
    )


class EgoFrameObservation(ObservationType):
    """The paper's flat ego-frame observation; see the module docstring for layout and scaling."""

    def __init__(self, env: PerceivingEnv, **kwargs) -> None:
        super().__init__(env)
        config = env.config
        self.n_waypoints, self.n_vehicles = config["reference_waypoints"], config["surrounding_vehicles"]
        position, speed = 1.0 / config["position_scale"], 1.0 / config["speed_scale"]
        # One multiplier per observation entry: scaling is then a single vector product.
        self.scale = np.concatenate(
            [
                [speed, speed, 1.0, 1.0, 1.0],
                np.tile([position, position, 1.0, 1.0], self.n_waypoints),
                np.tile([position, position, 1.0, 1.0, speed, 1.0], self.n_vehicles),
            ]
        )

    def space(self) -> spaces.Box:
        return spaces.Box(-np.inf, np.inf, shape=self.scale.shape, dtype=np.float32)

    def observe(self, scene: Scene | None = None) -> np.ndarray:
        """
        :param scene: the scene to observe (``step()`` passes the one it computed); by default the env's current state
        :return: the flat observation
        """
        if scene is None:
            scene = observe_scene(self.env)
        vehicles = np.zeros((self.n_vehicles, VEHICLE_FEATURES))
        nearest = scene.vehicles[: self.n_vehicles, :5]
        vehicles[: len(nearest), :5] = nearest
        vehicles[: len(nearest), 5] = 1.0
        obs = np.concatenate([scene.ego, scene.waypoints.ravel(), vehicles.ravel()]) * self.scale
        return obs.astype(np.float32)
