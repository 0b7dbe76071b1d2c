"""
Scripted drivers of the driving scenarios, baselines for evaluations: ``env.step(ScriptedDriver(env)(obs))``.
:class:`ScriptedDriver` reads only the observation (and the env's config for scales and bounds);
:class:`JunctionDriver` adds a gap acceptance at the intersection's stop line that reads the traffic's routes.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_dacerf.envs.driving import SCRIPTED_DRIVER_NAMES
from sb3_dacerf.envs.driving.common.abstract import PaperDrivingMixin
from sb3_dacerf.envs.driving.common.observation import EGO_FEATURES, VEHICLE_FEATURES, WAYPOINT_FEATURES
from sb3_dacerf.envs.driving.intersection import IntersectionEnv, travel_time


class ScriptedDriver:
    """
    Pure pursuit on the observed waypoints, a speed controller towards the target speed their spacing encodes, braking
    for the nearest vehicle in its corridor ahead and, with ``yield_to_crossing``, for any vehicle whose
    constant-velocity prediction comes within ``conflict_distance`` [m] of its path within ``horizon`` [s].

    :param env: a ``DACERF-Multilane-v0`` / ``DACERF-Intersection-v0`` env (wrapped or not)
    """

    def __init__(self, env: gym.Env, yield_to_crossing: bool = True, horizon: float = 2.5, conflict_distance: float = 3.0):
        unwrapped = env.unwrapped
        if not isinstance(unwrapped, PaperDrivingMixin) or not isinstance(env.action_space, spaces.Box):
            raise TypeError(
                "ScriptedDriver drives DACERF-Multilane-v0 and DACERF-Intersection-v0 (with their Box action space), "
                f"got {type(unwrapped).__name__} with action space {env.action_space}: pass one of those envs"
            )
        config = unwrapped.config
        self.position_scale, self.speed_scale = config["position_scale"], config["speed_scale"]
        self.n_waypoints, self.waypoint_interval = config["reference_waypoints"], config["reference_waypoint_interval"]
        self.length, self._unwrapped = unwrapped.vehicle.LENGTH, unwrapped
        self.yield_to_crossing, self.horizon, self.conflict_distance = yield_to_crossing, horizon, conflict_distance

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """:return: the action, for the flat observation of one env, towards the command this driver wants"""
        v_x = float(obs[0]) * self.speed_scale
        end = EGO_FEATURES + WAYPOINT_FEATURES * self.n_waypoints
        waypoints = obs[EGO_FEATURES:end].reshape(-1, WAYPOINT_FEATURES) * self.position_scale
        vehicles = obs[end:].reshape(-1, VEHICLE_FEATURES)
        vehicles = vehicles[vehicles[:, 5] > 0]
        reference_speed = float(np.hypot(*(waypoints[1, :2] - waypoints[0, :2])) / self.waypoint_interval)
        desired = np.array([self._acceleration(waypoints, vehicles, v_x, reference_speed), self._steering(waypoints, v_x)])
        return self._unwrapped.action_type.command_action(desired).astype(np.float32)

    def _steering(self, waypoints: np.ndarray, v_x: float) -> float:
        """Pure pursuit of the waypoint ~0.8 s of travel (at least 4 m) ahead."""
        distances = np.hypot(waypoints[:, 0], waypoints[:, 1])
        target = waypoints[min(int(np.searchsorted(distances, max(4.0, 0.8 * v_x))), self.n_waypoints - 1), :2]
        curvature = 2 * target[1] / max(target @ target, 1e-6)
        return float(np.arctan(2 * np.tan(np.arcsin(np.clip(curvature * self.length / 2, -1, 1)))))

    def _acceleration(self, waypoints: np.ndarray, vehicles: np.ndarray, v_x: float, reference_speed: float) -> float:
        """Towards the target speed; braking for the vehicle ahead and, with ``yield_to_crossing``, for conflicts."""
        desired_acceleration = 0.5 * (reference_speed - v_x)
        for x, y in vehicles[:, :2] * self.position_scale:
            gap = x - self.length
            if x > 0 and abs(y) < 2.5 and gap < 2.0 * max(v_x, 1.0) + 5:
                desired_acceleration = -1.0
        if self.yield_to_crossing and len(vehicles) and self._conflict(waypoints, vehicles, v_x):
            desired_acceleration = -1.0
        return desired_acceleration

    def _conflict(self, waypoints: np.ndarray, vehicles: np.ndarray, v_x: float) -> bool:
        """Whether a vehicle's constant-velocity prediction comes within ``conflict_distance`` of the ego's path."""
        times = np.arange(0.0, self.horizon + 1e-9, 0.25)
        # The ego moves along the waypoints at its speed, at least 2 m/s (a stopped ego checks it may go)
        path_s = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(waypoints[:, :2], axis=0).T))))
        ego_s = np.minimum(max(v_x, 2.0) * times, path_s[-1])
        ego = np.column_stack([np.interp(ego_s, path_s, waypoints[:, 0]), np.interp(ego_s, path_s, waypoints[:, 1])])
        for x, y, cos_phi, sin_phi, speed, _ in vehicles:
            position = np.array([x, y]) * self.position_scale
            if position[0] < 0 and cos_phi > 0.9:
                continue  # following the ego in its direction: not ours to yield to
            velocity = speed * self.speed_scale * np.array([cos_phi, sin_phi])
            other = position + times[:, None] * velocity
            if np.min(np.hypot(*(other - ego).T)) < self.conflict_distance:
                return True
        return False


class JunctionDriver(ScriptedDriver):
    """
    A gap-accepting driver for ``DACERF-Intersection-v0``: tracking as :class:`ScriptedDriver` does, and before the
    stop line checking its crossing against the time windows of the traffic within 80 m on its path (along their
    planned routes; vehicles are three circles, paths conflict within 3.1 m). It brakes to stop before a conflict (at
    the line at the latest) unless it no longer can; in the junction it brakes only for the vehicle ahead.
    """

    CIRCLE_OFFSETS = np.array([-1.67, 0.0, 1.67])  #: [m] the circles covering a 5 m x 2 m vehicle, along its axis
    PREDICTION_DISTANCES = np.arange(0.0, 80.0, 1.0)  #: [m] along each traffic vehicle's route, where it is predicted
    TRAFFIC_ACCELERATION, TRAFFIC_MAX_SPEED, TRAFFIC_MIN_SPEED, MARGIN = 3.0, 9.0, 2.0, 1.0
    """A traffic vehicle arrives no earlier than accelerating at [m/s²] up to [m/s], leaves no later than at [m/s],
    each widened by [s]."""
    EGO_ACCELERATION, APPROACH_DECELERATION = 0.7, 0.5
    """[m/s²] of the ego's crossing plan (up to its target speed) and at most of its approach to a stop."""

    def __init__(self, env: gym.Env):
        super().__init__(env, yield_to_crossing=False, conflict_distance=3.1)
        if not isinstance(env.unwrapped, IntersectionEnv):
            raise TypeError(
                f"JunctionDriver drives DACERF-Intersection-v0, got {type(env.unwrapped).__name__}: use ScriptedDriver"
            )
        self.braking = -float(env.unwrapped.config["acceleration_range"][0])

    def _acceleration(self, waypoints: np.ndarray, vehicles: np.ndarray, v_x: float, reference_speed: float) -> float:
        desired = 0.5 * (reference_speed - v_x)
        for x, y, cos_phi in zip(*(vehicles[:, :2] * self.position_scale).T, vehicles[:, 2], strict=True):
            gap = x - self.length
            in_corridor = x > 0 and abs(y) < 2.5
            if in_corridor and ((cos_phi > 0.5 and gap < 2.0 * max(v_x, 1.0) + 5) or gap < 4.0):
                desired = -1.0
        to_line = self._unwrapped.front_to_line()
        if to_line > -0.5:  # not yet committed to the junction
            stop = self._stop_point(waypoints[:, :2], v_x, reference_speed, to_line)
            if stop is not None:
                room = stop - self.length / 2 - 1.0
                allowed = min(np.sqrt(2 * self.APPROACH_DECELERATION * max(room, 0.0)), reference_speed)
                approach = -self.braking if room <= 0.5 else float(np.clip(allowed - v_x, -self.braking, self.braking))
                desired = min(desired, approach)
        return desired

    def _stop_point(self, waypoints: np.ndarray, v_x: float, reference_speed: float, to_line: float) -> float | None:
        """The arc length along the ego's path [m] of the nearest conflict it must and can stop before, if any."""
        # the ego's path (its position, the waypoints and 30 m straight on) every 0.5 m, with the times of its plan
        points = np.vstack([[0.0, 0.0], waypoints])
        heading = (points[-1] - points[-2]) / max(float(np.linalg.norm(points[-1] - points[-2])), 1e-6)
        points = np.vstack([points, points[-1] + np.outer(np.arange(1.0, 31.0), heading)])
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points, axis=0).T))])
        s = np.arange(0.0, arc[-1], 0.5)
        if len(s) < 2:  # the waypoints gathered at the ego (a reference speed of 0): nothing to check
            return None
        path = np.column_stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])])
        times = travel_time(s, max(v_x, 0.0), self.EGO_ACCELERATION, max(reference_speed, v_x))
        tangents = np.gradient(path, axis=0)
        tangents /= np.maximum(np.linalg.norm(tangents, axis=1, keepdims=True), 1e-9)
        ego_circles = path[:, None, :] + self.CIRCLE_OFFSETS[None, :, None] * tangents[:, None, :]
        low, high = path.min(axis=0) - 6.0, path.max(axis=0) + 6.0
        stopping = v_x**2 / (2 * self.braking) + 0.1 * v_x
        occupancy = 3.0  # [m] before and after the conflicting stretch that the ego's body still covers
        stops = []
        for speed, route, directions in self._predictions():
            near = np.all((route > low) & (route < high), axis=1)
            if not near.any():
                continue
            distances = self.PREDICTION_DISTANCES[near]
            circles = route[near][:, None, :] + self.CIRCLE_OFFSETS[None, :, None] * directions[near][:, None, :]
            gaps = np.linalg.norm(circles[:, None, :, None, :] - ego_circles[None, :, None, :, :], axis=-1).min(axis=(2, 3))
            traffic_index, ego_index = np.nonzero(gaps < self.conflict_distance)
            if len(traffic_index) == 0:
                continue
            s_in, s_out = s[ego_index].min(), s[ego_index].max()
            first, last = distances[traffic_index].min(), distances[traffic_index].max()
            traffic_in = float(travel_time(first, speed, self.TRAFFIC_ACCELERATION, self.TRAFFIC_MAX_SPEED))
            traffic_out = last / max(speed, self.TRAFFIC_MIN_SPEED)
            ego_in = float(np.interp(s_in - occupancy, s, times)) if s_in > occupancy else 0.0
            ego_out = float(np.interp(s_out + occupancy, s, times))
            if (
                ego_in < traffic_out + self.MARGIN
                and traffic_in - self.MARGIN < ego_out
                and stopping <= s_in - self.length / 2 + 0.5
            ):
                stops.append(s_in)
        if not stops:
            return None
        stop = min(stops)
        line_stop = to_line + self.length / 2 + 1.0
        return line_stop if line_stop < stop and stopping <= to_line + 0.5 else stop

    def _predictions(self) -> list[tuple[float, np.ndarray, np.ndarray]]:
        """
        Each traffic vehicle within 80 m that may cross the ego's path (not one ahead in its lane nor one behind it),
        in the ego's frame: speed, positions along its planned route at ``PREDICTION_DISTANCES`` and heading vectors.
        """
        env, ego = self._unwrapped, self._unwrapped.vehicle
        cos_h, sin_h = np.cos(ego.heading), np.sin(ego.heading)
        rotation = np.array([[cos_h, sin_h], [-sin_h, cos_h]])
        predictions = []
        for vehicle in env.road.vehicles:
            if vehicle is ego or np.linalg.norm(vehicle.position - ego.position) > 80.0:
                continue
            position = rotation @ (vehicle.position - ego.position)
            if np.cos(vehicle.heading - ego.heading) > 0.87 and (abs(position[1]) < 3.0 or position[0] < 0):
                continue
            route = list(getattr(vehicle, "route", None) or [vehicle.lane_index])
            if route[0][:2] != vehicle.lane_index[:2]:
                route = [vehicle.lane_index, *route]
            start = vehicle.lane.local_coordinates(vehicle.position)[0]
            along = [
                env.road.network.position_heading_along_route(route, start + d, 0.0, vehicle.lane_index)
                for d in self.PREDICTION_DISTANCES
            ]
            positions = (np.array([p for p, _ in along]) - ego.position) @ rotation.T
            headings = np.array([h for _, h in along]) - ego.heading
            predictions.append((float(vehicle.speed), positions, np.column_stack([np.cos(headings), np.sin(headings)])))
        return predictions


#: The drivers by the names the command-line tools give them
SCRIPTED_DRIVERS: dict[str, type[ScriptedDriver]] = dict(
    zip(SCRIPTED_DRIVER_NAMES, (ScriptedDriver, JunctionDriver), strict=True)
)
