"""
What the ego perceives (:class:`Scene`, computed once per step) and the paper's flat ``float32`` ego-frame
observation of it (x along the ego heading, y along highway-env's lateral axis):

- ego ``[v_x / speed_scale, v_y / speed_scale, r, a_x, δ]``: body-frame velocity, yaw rate, commanded a_x and δ;
- W = ``reference_waypoints`` waypoints ``[x / position_scale, y / position_scale, cos φ, sin φ]`` from the ego's
  projection on the reference, every ``reference_waypoint_interval`` seconds of travel at the target speed (so their
  spacing encodes it), φ relative to the ego heading;
- M = ``surrounding_vehicles`` vehicles within ``perception_distance``, nearest first, ``[x / position_scale,
  y / position_scale, cos φ, sin φ, v / speed_scale, mask]`` (relative position and heading, speed); padding rows 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces
from highway_env import utils
from highway_env.envs.common.observation import ObservationType

EGO_FEATURES = 5
WAYPOINT_FEATURES = 4
VEHICLE_FEATURES = 6


def vehicle_rows(config: dict) -> tuple[int, int, int]:
    """:return: the start, number and length (mask last) of the vehicle rows of a driving env's observation"""
    return EGO_FEATURES + WAYPOINT_FEATURES * config["reference_waypoints"], config["surrounding_vehicles"], VEHICLE_FEATURES


@dataclass
class Scene:
    """What the ego perceives at one step, in SI units and in the ego frame."""

    ego: np.ndarray  # [v_x, v_y, r, a_x, δ]
    waypoints: np.ndarray  # (W, 4) [x, y, cos φ, sin φ]
    vehicles: np.ndarray  # (K, 7) within perception distance, nearest first: [x, y, cos φ, sin φ, v, length, width]
    lateral_error: float
    heading_error: float
    reference_curvature: float
    road_clearance: float  # from the ego centre to the road edge [m], negative off the road
    reference_progress: float = 0.0  # arc length of the ego's projection on its reference [m]
    reference_speed: float = 0.0  # the (capped) target speed the waypoints are spaced by and the tracking term asks for


def vehicle_gaps(vehicles: np.ndarray, ego_length: float, ego_width: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    :param vehicles: the scene's vehicles, ego frame, ``[x, y, cos φ, sin φ, v, length, width]`` rows
    :return: the longitudinal and lateral clearances [m] between the ego's body and theirs (negative: overlapping along
        that axis), and the mask of the vehicles in the ego's corridor ahead
    """
    x, y = vehicles[:, 0], vehicles[:, 1]
    gap_long = np.abs(x) - (ego_length + vehicles[:, 5]) / 2
    gap_lat = np.abs(y) - (ego_width + vehicles[:, 6]) / 2
    return gap_long, gap_lat, (x > 0) & (gap_lat < 0)


def observe_scene(env: Any) -> Scene:
    """:return: what the ego of a driving env (after ``reset()``) perceives in its current state"""
    config = env.config
    ego = env.vehicle
    beta = math.atan(0.5 * math.tan(ego.action["steering"]))
    v_x, v_y = ego.speed * math.cos(beta), ego.speed * math.sin(beta)
    ego_state = np.array([v_x, v_y, v_y / (ego.LENGTH / 2), *env.action_type.command])  # r: the bicycle model's yaw rate
    cos_h, sin_h = math.cos(ego.heading), math.sin(ego.heading)
    to_ego_frame_t = np.array([[cos_h, -sin_h], [sin_h, cos_h]])

    vehicles = np.zeros((0, 7))
    others = [v for v in env.road.vehicles if v is not ego]
    if others:
        # [x, y, heading, speed, length, width] per vehicle, then vectorised
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
    reference_speed = min(env.reference_speed, env.reference_speed_cap(), env.reference_speed_ceiling)
    step = reference_speed * config["reference_waypoint_interval"]
    points, headings, curvatures = env.reference.at(s + step * np.arange(config["reference_waypoints"]))
    relative_headings = headings - ego.heading
    waypoints = np.empty((len(points), WAYPOINT_FEATURES))
    waypoints[:, :2] = (points - ego.position) @ to_ego_frame_t
    waypoints[:, 2], waypoints[:, 3] = np.cos(relative_headings), np.sin(relative_headings)

    heading_error = float(utils.wrap_to_pi(ego.heading - float(headings[0])))
    clearance = env._road_clearance(ego.position)
    return Scene(ego_state, waypoints, vehicles, lateral, heading_error, float(curvatures[0]), clearance, s, reference_speed)


class EgoFrameObservation(ObservationType):
    """The paper's flat ego-frame observation; see the module docstring for layout and scaling."""

    def __init__(self, env: Any) -> None:
        super().__init__(env)
        config = env.config
        self.n_waypoints, self.n_vehicles = config["reference_waypoints"], config["surrounding_vehicles"]
        position, speed = 1.0 / config["position_scale"], 1.0 / config["speed_scale"]
        waypoint, vehicle = [position, position, 1.0, 1.0], [position, position, 1.0, 1.0, speed, 1.0]
        # one multiplier per observation entry
        self.scale = np.concatenate(
            [[speed, speed, 1.0, 1.0, 1.0], np.tile(waypoint, self.n_waypoints), np.tile(vehicle, self.n_vehicles)]
        )

    def space(self) -> spaces.Box:
        return spaces.Box(-np.inf, np.inf, shape=self.scale.shape, dtype=np.float32)

    def observe(self, scene: Scene | None = None) -> np.ndarray:
        """:param scene: the scene to observe (``step()`` passes the one it computed), by default the env's current one"""
        if scene is None:
            scene = observe_scene(self.env)
        vehicles = np.zeros((self.n_vehicles, VEHICLE_FEATURES))
        nearest = scene.vehicles[: self.n_vehicles, :5]
        vehicles[: len(nearest), :5] = nearest
        vehicles[: len(nearest), 5] = 1.0
        obs = np.concatenate([scene.ego, scene.waypoints.ravel(), vehicles.ravel()]) * self.scale
        return obs.astype(np.float32)
