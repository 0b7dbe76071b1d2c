"""
Faster drop-in versions of highway-env's road, lane network and IDM vehicle, on which the driving scenarios' traffic
runs. Every answer is highway-env's (the same closest lane, neighbours, right-of-way conflicts, IDM decisions and
collisions: ``tests/test_driving_simulation.py`` checks each piece and whole episodes against highway-env's classes);
``benchmarks/driving_speed.py`` measures the speed-up.
"""

from __future__ import annotations

import copy
import math
from collections import deque
from typing import Any

import numpy as np
from highway_env import utils
from highway_env.road.lane import AbstractLane, CircularLane, StraightLane
from highway_env.road.regulation import RegulatedRoad
from highway_env.road.road import LaneIndex, Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Landmark, RoadObject

_TOLERANCE = 1e-9  # [m] margin of every bound, so that rounding never rules out the right answer
_ARC_SAMPLING = 0.5  # [m] spacing of the points that bound an arc lane's box (widened by as much: > its sagitta)
Bound = tuple[bool | None, float, float, float, float, float, float]


class _Remembering:
    """A lane (mixed in before its class) remembering the local coordinates of the last positions asked."""

    _memory: dict[bytes, tuple[float, float]]

    def local_coordinates(self, position: np.ndarray) -> tuple[float, float]:
        if type(position) is not np.ndarray or position.dtype != np.float64 or position.shape != (2,):
            return super().local_coordinates(position)  # type: ignore[misc]
        key = position.tobytes()  # the exact bits (-0.0 and 0.0 are two keys)
        coordinates = self._memory.get(key)
        if coordinates is None:
            if len(self._memory) >= 4096:
                self._memory.clear()
            coordinates = self._memory[key] = super().local_coordinates(position)  # type: ignore[misc]
        return coordinates

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_memory": {}}


class RememberingStraightLane(_Remembering, StraightLane):
    pass


class RememberingCircularLane(_Remembering, CircularLane):
    pass


_REMEMBERING: dict[type, type] = {StraightLane: RememberingStraightLane, CircularLane: RememberingCircularLane}
_STRAIGHT, _CIRCULAR = (StraightLane, RememberingStraightLane), (CircularLane, RememberingCircularLane)


def _lane_bound(lane: AbstractLane) -> Bound:
    """
    ``(straight, x_min, y_min, x_max, y_max, heading, half_width)``, a lower bound of ``lane.distance_with_heading``
    (``straight`` ``None``: none): the distance to the centre line's box, plus a straight lane's heading difference or
    at least the angle to an arc's headings (beyond its ends the position term grows faster, for radii >= 1 m).
    """
    if type(lane) in _STRAIGHT:
        (x0, y0), (x1, y1) = lane.start, lane.end
        return True, min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1), float(lane.heading), 0.0
    if type(lane) in _CIRCULAR and lane.radius >= 1.0:
        samples = np.linspace(0.0, lane.length, max(math.ceil(abs(lane.length) / _ARC_SAMPLING), 1) + 1)
        points = np.array([lane.position(s, 0.0) for s in samples])
        low, high = points.min(axis=0) - _ARC_SAMPLING, points.max(axis=0) + _ARC_SAMPLING
        start, end = lane.heading_at(0.0), lane.heading_at(lane.length)
        return False, low[0], low[1], high[0], high[1], float((start + end) / 2), float(abs(end - start) / 2)
    return None, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0


class IndexedRoadNetwork(RoadNetwork):
    """
    highway-env's ``RoadNetwork``; ``get_closest_lane_index`` measures the lanes nearest first (by their bound over the
    position's grid cell), skipping those whose bound exceeds the best distance found (ties: the first lane, as
    ``np.argmin``).
    """

    CELL = 2.0
    """[m] side of the grid cells whose lanes' order is remembered."""
    MAX_CELLS = 65536
    _bounds: list[tuple[LaneIndex, AbstractLane, Bound]] | None = None
    _cells: dict[tuple[int, int], list[tuple[float, int]]]

    @classmethod
    def from_network(cls, network: RoadNetwork) -> IndexedRoadNetwork:
        """:return: an indexed network of the lanes of ``network``, its straight and arc lanes made remembering"""
        indexed = cls()
        indexed.graph = network.graph
        for lane in indexed.lanes_list():
            if type(lane) in _REMEMBERING:
                lane.__class__, lane._memory = _REMEMBERING[type(lane)], {}  # type: ignore[attr-defined]
        return indexed

    def __getstate__(self) -> dict:
        # the bounds and cells are rebuilt on demand: a pickled network stays small
        return {key: value for key, value in self.__dict__.items() if key not in ("_bounds", "_cells")}

    def add_lane(self, _from: str, _to: str, lane: AbstractLane) -> None:
        super().add_lane(_from, _to, lane)
        self._bounds = None

    def _lane_bounds(self) -> list[tuple[LaneIndex, AbstractLane, Bound]]:
        if self._bounds is None:
            self._cells = {}
            self._bounds = [
                ((_from, _to, _id), lane, _lane_bound(lane))
                for _from, to_dict in self.graph.items()
                for _to, lanes in to_dict.items()
                for _id, lane in enumerate(lanes)
            ]
        return self._bounds

    def get_closest_lane_index(self, position: np.ndarray, heading: float | None = None) -> LaneIndex:
        """``RoadNetwork.get_closest_lane_index``'s answer; positions or headings that are not finite go to it."""
        x, y = float(position[0]), float(position[1])
        h = None if heading is None else float(heading)
        if not (math.isfinite(x) and math.isfinite(y) and (h is None or math.isfinite(h))):
            return super().get_closest_lane_index(position, heading)
        lanes = self._lane_bounds()
        cell = (math.floor(x / self.CELL), math.floor(y / self.CELL))
        candidates = self._cells.get(cell) or self._cell_candidates(cell)
        best, best_i = math.inf, -1
        for cell_bound, i in candidates:
            if cell_bound > best:
                break  # this lane and the next ones are farther than the best lane, wherever in the cell
            _, lane, (straight, x_min, y_min, x_max, y_max, lane_heading, half_width) = lanes[i]
            if straight is not None:
                dx = x_min - x if x < x_min else (x - x_max if x > x_max else 0.0)
                dy = y_min - y if y < y_min else (y - y_max if y > y_max else 0.0)
                bound = math.hypot(dx, dy)
                if h is not None:
                    angle = abs((h - lane_heading + math.pi) % (2 * math.pi) - math.pi) - half_width
                    if angle > 0.0:
                        bound = bound + angle if straight else max(bound, angle)
                if bound - _TOLERANCE > best:
                    continue
            distance = lane.distance_with_heading(position, heading)
            if distance < best or (distance == best and i < best_i):
                best, best_i = distance, i
        return lanes[best_i][0]

    def _cell_candidates(self, cell: tuple[int, int]) -> list[tuple[float, int]]:
        """:return: each lane's bound over the cell (``-inf`` without a bound) and its index, nearest first"""
        if len(self._cells) >= self.MAX_CELLS:
            self._cells.clear()
        x0, y0 = cell[0] * self.CELL, cell[1] * self.CELL
        x1, y1 = x0 + self.CELL, y0 + self.CELL
        candidates = []
        for i, (_, _, (straight, x_min, y_min, x_max, y_max, _, _)) in enumerate(self._lane_bounds()):
            dx, dy = max(x_min - x1, x0 - x_max, 0.0), max(y_min - y1, y0 - y_max, 0.0)
            candidates.append((-math.inf if straight is None else math.hypot(dx, dy) - _TOLERANCE, i))
        self._cells[cell] = candidates = sorted(candidates)
        return candidates


def _lateral_filter(lane: AbstractLane) -> Any:
    """
    :return: ``far(position)``, true only for positions that ``lane.on_lane(..., margin=1)`` rejects for their lateral
        offset (computed in a few float operations, with a tolerance for rounding); ``None`` for other kinds of lanes
    """
    if type(lane) in _STRAIGHT:
        (x0, y0), (nx, ny) = lane.start, lane.direction_lateral
        x0, y0, nx, ny = float(x0), float(y0), float(nx), float(ny)
        limit = lane.width / 2 + 1.0 + _TOLERANCE
        return lambda position: abs((position[0] - x0) * nx + (position[1] - y0) * ny) > limit
    if type(lane) in _CIRCULAR:
        (cx, cy), radius = lane.center, lane.radius
        cx, cy = float(cx), float(cy)
        limit = lane.width / 2 + 1.0 + _TOLERANCE
        return lambda position: abs(radius - math.hypot(position[0] - cx, position[1] - cy)) > limit
    return None


def _may_touch(vehicle: Any, other: Any, dt: float) -> bool:
    """Whether ``vehicle.handle_collisions(other, dt)`` may do anything: false where highway-env's own pre-check returns."""
    methods = type(vehicle)._is_colliding, type(vehicle).handle_collisions
    if methods != (RoadObject._is_colliding, RoadObject.handle_collisions):  # another check than highway-env's
        return True
    reach = (vehicle.diagonal + other.diagonal) / 2 + vehicle.speed * dt + _TOLERANCE
    position, other_position = vehicle.position, other.position
    return abs(other_position[0] - position[0]) <= reach and abs(other_position[1] - position[1]) <= reach


class FastRoad(Road):
    """highway-env's ``Road`` with a faster neighbour search and collision loop (the same answers)."""

    _lane_coordinates: dict[int, list[tuple[Any, float]]] | None = None

    def act(self) -> None:
        """``Road.act()``; vehicles do not move while they decide, so each lane's vehicles are collected once."""
        self._lane_coordinates = {}
        try:
            super().act()
        finally:
            self._lane_coordinates = None

    def _coordinates_on(self, lane: AbstractLane) -> list[tuple[Any, float]]:
        """:return: the vehicles and objects on a lane (with highway-env's 1 m margin) and their longitudinal coordinate"""
        on_lane = []
        far = _lateral_filter(lane)
        for v in self.vehicles + self.objects:
            if isinstance(v, Landmark) or (far is not None and far(v.position)):
                continue
            s_v, lat_v = lane.local_coordinates(v.position)
            if lane.on_lane(v.position, s_v, lat_v, margin=1):
                on_lane.append((v, s_v))
        return on_lane

    def neighbour_vehicles(self, vehicle: RoadObject, lane_index: LaneIndex | None = None) -> tuple[Any, Any]:
        """``Road.neighbour_vehicles``'s answer: the vehicles just ahead of and behind a vehicle on a lane."""
        cache = self._lane_coordinates
        if cache is None or self.neighbour_vehicles_connected_lanes:
            return super().neighbour_vehicles(vehicle, lane_index)
        lane_index = lane_index or vehicle.lane_index
        if not lane_index:
            return None, None
        lane = self.network.get_lane(lane_index)
        coordinates = cache.get(id(lane))
        if coordinates is None:
            coordinates = cache[id(lane)] = self._coordinates_on(lane)
        s = lane.local_coordinates(vehicle.position)[0]
        s_front = s_rear = v_front = v_rear = None
        for v, s_v in coordinates:
            if v is vehicle:
                continue
            if s <= s_v and (s_front is None or s_v <= s_front):
                s_front, v_front = s_v, v
            if s_v < s and (s_rear is None or s_v > s_rear):
                s_rear, v_rear = s_v, v
        return v_front, v_rear

    def step(self, dt: float) -> None:
        """``Road.step``: move every vehicle, then resolve collisions in the same order, without the calls that do nothing."""
        vehicles = self.vehicles
        for vehicle in vehicles:
            vehicle.step(dt)
        checking = [j for j, vehicle in enumerate(vehicles) if vehicle.check_collisions]
        for i, vehicle in enumerate(vehicles):
            others = vehicles[i + 1 :] if vehicle.check_collisions else [vehicles[j] for j in checking if j > i]
            for other in others:
                if _may_touch(vehicle, other, dt):
                    vehicle.handle_collisions(other, dt)
            for other in self.objects:
                vehicle.handle_collisions(other, dt)


def predict_constant_speed(vehicle: Vehicle, times: np.ndarray) -> tuple[list[np.ndarray], list[float]]:
    """``vehicle.predict_trajectory_constant_speed(times)`` without the deep copy of the road (its kinematics read none)."""
    if type(vehicle).predict_trajectory_constant_speed is not Vehicle.predict_trajectory_constant_speed:
        return vehicle.predict_trajectory_constant_speed(times)
    detached = copy.copy(vehicle)
    detached.road, detached.lane, detached.history, detached.log = None, None, deque(maxlen=vehicle.history.maxlen), []
    return Vehicle.predict_trajectory_constant_speed(detached, times)


class FastRegulatedRoad(RegulatedRoad, FastRoad):
    """highway-env's ``RegulatedRoad`` (junction right of way) on :class:`FastRoad`, predicting each vehicle once."""

    _predictions: dict[tuple[int, int, float], tuple[np.ndarray, np.ndarray, tuple[float, ...]]] | None = None

    def enforce_road_rules(self) -> None:
        """``RegulatedRoad.enforce_road_rules()``; the states do not change meanwhile, so each prediction is made once."""
        self._predictions = {}
        try:
            super().enforce_road_rules()
        finally:
            self._predictions = None

    def _prediction(self, vehicle: Vehicle, horizon: int, step: float) -> tuple[np.ndarray, np.ndarray, tuple[float, ...]]:
        assert self._predictions is not None
        key = (id(vehicle), horizon, step)
        if key not in self._predictions:
            positions, headings = predict_constant_speed(vehicle, np.arange(step, horizon, step))
            points = np.array(positions, dtype=float).reshape(-1, 2)
            box = (*points.min(axis=0), *points.max(axis=0)) if len(points) else (math.inf, math.inf, -math.inf, -math.inf)
            self._predictions[key] = (points, np.asarray(headings, dtype=float), box)
        return self._predictions[key]

    def is_conflict_possible(self, v1: Vehicle, v2: Vehicle, horizon: int = 3, step: float = 0.25) -> bool:
        """``RegulatedRoad.is_conflict_possible``'s answer: whether the predicted rectangles meet within ``horizon`` s."""
        if self._predictions is None:
            return bool(RegulatedRoad.is_conflict_possible(v1, v2, horizon, step))
        points_1, headings_1, box_1 = self._prediction(v1, horizon, step)
        points_2, headings_2, box_2 = self._prediction(v2, horizon, step)
        reach = v1.LENGTH + _TOLERANCE
        # Paths that never come within reach: highway-env's pre-check skips every time.
        if any(gap > reach for gap in (box_2[0] - box_1[2], box_1[0] - box_2[2], box_2[1] - box_1[3], box_1[1] - box_2[3])):
            return False
        count = min(len(points_1), len(points_2))
        gaps = points_2[:count] - points_1[:count]
        # The times highway-env's pre-check may keep (with a margin for rounding), then its own checks on them.
        for k in np.flatnonzero(np.sqrt(gaps[:, 0] * gaps[:, 0] + gaps[:, 1] * gaps[:, 1]) <= reach):
            if np.linalg.norm(gaps[k]) <= v1.LENGTH and utils.rotated_rectangles_intersect(
                (points_1[k], 1.5 * v1.LENGTH, 0.9 * v1.WIDTH, headings_1[k]),
                (points_2[k], 1.5 * v2.LENGTH, 0.9 * v2.WIDTH, headings_2[k]),
            ):
                return True
        return False


def _clip(value: Any, low: float, high: float) -> Any:
    """``np.clip`` of one number (the same value, NaN included), without converting it to an array and back."""
    return low if value < low else (high if value > high else value)


class FastIDMVehicle(IDMVehicle):
    """highway-env's ``IDMVehicle`` clipping Python numbers, not with ``np.clip`` (numpy's trigonometry is kept: same bits)."""

    def steering_control(self, target_lane_index: LaneIndex) -> float:
        """``ControlledVehicle.steering_control``'s steering angle [rad] towards a lane's centre."""
        lane = self.road.network.get_lane(target_lane_index)
        longitudinal, lateral = lane.local_coordinates(self.position)
        speed = utils.not_zero(self.speed)
        lane_heading_ahead = lane.heading_at(longitudinal + self.speed * self.TAU_PURSUIT)
        heading_offset = np.arcsin(_clip(-self.KP_LATERAL * lateral / speed, -1, 1))
        heading_reference = lane_heading_ahead + _clip(heading_offset, -np.pi / 4, np.pi / 4)
        heading_rate = self.KP_HEADING * utils.wrap_to_pi(heading_reference - self.heading)
        slip_angle = np.arcsin(_clip(self.LENGTH / 2 / speed * heading_rate, -1, 1))
        steering = np.arctan(2 * np.tan(slip_angle))
        return float(_clip(steering, -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE))

    def acceleration(self, ego_vehicle: Any, front_vehicle: Any = None, rear_vehicle: Any = None) -> float:
        """``IDMVehicle.acceleration``'s IDM acceleration [m/s²] of ``ego_vehicle`` behind ``front_vehicle``."""
        if not ego_vehicle or not isinstance(ego_vehicle, Vehicle):
            return 0
        target_speed = getattr(ego_vehicle, "target_speed", 0)
        lane = ego_vehicle.lane
        if lane and lane.speed_limit is not None:
            target_speed = _clip(target_speed, 0, lane.speed_limit)
        free_road = np.power(max(ego_vehicle.speed, 0) / abs(utils.not_zero(target_speed)), self.DELTA)
        acceleration = self.COMFORT_ACC_MAX * (1 - free_road)
        if front_vehicle:
            gap = ego_vehicle.lane_distance_to(front_vehicle)
            acceleration -= self.COMFORT_ACC_MAX * np.power(self.desired_gap(ego_vehicle, front_vehicle) / utils.not_zero(gap), 2)
        return acceleration

    def act(self, action: dict | str | None = None) -> None:
        """``IDMVehicle.act``'s decision: MOBIL lane change, steering, IDM acceleration (on the target lane too)."""
        if self.crashed:
            return
        self.follow_road()
        if self.enable_lane_change:
            self.change_lane_policy()
        steering = self.steering_control(self.target_lane_index)  # already within MAX_STEERING_ANGLE
        front, rear = self.road.neighbour_vehicles(self, self.lane_index)
        acceleration = self.acceleration(ego_vehicle=self, front_vehicle=front, rear_vehicle=rear)
        if self.lane_index != self.target_lane_index:
            front, rear = self.road.neighbour_vehicles(self, self.target_lane_index)
            acceleration = min(acceleration, self.acceleration(ego_vehicle=self, front_vehicle=front, rear_vehicle=rear))
        Vehicle.act(self, {"steering": steering, "acceleration": _clip(acceleration, -self.ACC_MAX, self.ACC_MAX)})


def fast_road(road: Road, road_class: type[Road] = FastRoad) -> Road:
    """:return: ``road`` (without vehicles yet) rebuilt as a ``road_class`` on an :class:`IndexedRoadNetwork`"""
    return road_class(
        network=IndexedRoadNetwork.from_network(road.network),
        np_random=road.np_random,
        record_history=road.record_history,
        neighbour_vehicles_connected_lanes=road.neighbour_vehicles_connected_lanes,
    )


def fast_vehicle_class(vehicle_class: Any) -> Any:
    """:return: :class:`FastIDMVehicle` for highway-env's ``IDMVehicle``, any other traffic class as it is"""
    return FastIDMVehicle if vehicle_class is IDMVehicle else vehicle_class
