"""
Faster drop-in versions of highway-env's road, lane network and IDM vehicle, which give the simulation the same
answers.

The driving scenarios spend most of their time in four parts of highway-env's traffic simulation:

- ``RoadNetwork.get_closest_lane_index``, called after every move of every vehicle, measures the distance from the
  vehicle to every lane of the network (20 lanes at the intersection). :class:`IndexedRoadNetwork` bounds each
  lane's distance from below (the distance to the lane's bounding box, from the vehicle's 2 m grid cell and then
  from its position, and the heading difference) and measures the lanes nearest first, only while their bound does
  not exceed the best distance found: the same lane, ties going to the first in the network's order as
  ``np.argmin`` gives them. Its straight and arc lanes remember the local coordinates of recent positions (a
  position is projected on the same lane by the closest-lane search, the lane controller and the IDM gaps).
- ``Road.neighbour_vehicles`` (IDM and MOBIL: the vehicles ahead and behind on a lane) projects every vehicle on
  the lane for every query, several queries per vehicle and step. :class:`FastRoad` collects the vehicles on each
  lane once per ``Road.act()`` (positions do not change while vehicles decide), projecting only those whose lateral
  offset, computed in a few float operations, does not already put them off the lane, and scans that list. Its
  ``step()`` also skips the collision checks that highway-env returns from at once: pairs neither of which checks
  collisions (the multi-lane traffic) and pairs farther apart than highway-env's own pre-check distance.
- ``RegulatedRoad.enforce_road_rules`` (the intersection's right of way, twice a second) predicts both vehicles of
  every pair over 3 s, and a plain ``Vehicle`` (the ego) predicts itself by rolling out a ``copy.deepcopy`` of
  itself, which copies the whole road with every vehicle on it, and looks up its closest lane at each of the 11
  predicted points. :class:`FastRegulatedRoad` predicts each vehicle once per enforcement (the states do not change
  while the rules are enforced), rolls the ego out detached from the road (the same kinematics: the closest lane of
  a predicted point does not move it), and rejects pairs whose predicted paths stay farther apart than the
  conflict check's pre-check distance before comparing them point by point.
- ``IDMVehicle`` clips single numbers with ``np.clip`` (microseconds each, seven per decision):
  :class:`FastIDMVehicle` takes the same decisions clipping Python numbers.

Every answer is highway-env's own: the same lane, the same neighbours, the same conflicts and decisions, so the same
traffic and the same episodes for the same seed (``tests/test_driving_simulation.py`` checks each piece against
highway-env's and whole episodes against highway-env's classes). The scenarios use these classes unless their
config sets ``fast_simulation`` to ``False``.
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

_TWO_PI = 2 * math.pi
_BOUND_TOLERANCE = 1e-9
"""[m] subtracted from every lower bound, so that rounding can never rule out the closest lane."""
_ARC_SAMPLING = 0.5
"""[m] spacing of the points that bound an arc lane's box (widened by this much: more than the arc's sagitta)."""
_STRAIGHT, _ARC, _OTHER = 0, 1, 2


def _lane_bound(lane: AbstractLane) -> tuple[int, float, float, float, float, float, float]:
    """
    What bounds a lane's ``distance_with_heading`` from below.

    The position term ``|r| + max(s - L, 0) + max(-s, 0)`` of a straight or arc lane is at least the Euclidean
    distance to the lane's centre line (the point at the clamped ``s``; on an arc, the chord to the end point is
    shorter than the arc beyond it), so at least the distance to the line's bounding box. The heading term of a
    straight lane is the same everywhere; an arc's heading runs over an interval of half-width ``L / (2 R)``, and
    beyond either end the position term grows faster than the heading term can shrink (for ``R >= 1`` m), so the
    distance is at least the angle to that interval.

    :param lane: a lane of the network
    :return: ``(kind, x_min, y_min, x_max, y_max, heading, half_width)``, kind ``_STRAIGHT``, ``_ARC`` or ``_OTHER``
        (no bound: the lane is always measured)
    """
    if type(lane) in (StraightLane, RememberingStraightLane):
        (x0, y0), (x1, y1) = lane.start, lane.end
        return _STRAIGHT, min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1), float(lane.heading), 0.0
    if type(lane) in (CircularLane, RememberingCircularLane) and lane.radius >= 1.0:
        samples = np.linspace(0.0, lane.length, max(math.ceil(abs(lane.length) / _ARC_SAMPLING), 1) + 1)
        points = np.array([lane.position(s, 0.0) for s in samples])
        low, high = points.min(axis=0) - _ARC_SAMPLING, points.max(axis=0) + _ARC_SAMPLING
        start, end = lane.heading_at(0.0), lane.heading_at(lane.length)
        return _ARC, low[0], low[1], high[0], high[1], float((start + end) / 2), float(abs(end - start) / 2)
    return _OTHER, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0


class _RememberedCoordinates:
    """
    A lane that remembers the local coordinates of the positions it was last asked about (``local_coordinates`` is
    a function of the position alone): within a simulation step the same vehicle position is projected on the same
    lane by its controller, its neighbour search, the IDM gaps of the vehicles around it and the closest-lane search.
    Mixed in before a highway-env lane class; the memory is emptied when it holds ``MEMORY`` positions.
    """

    MEMORY = 4096
    _memory: dict[bytes, tuple[float, float]]

    def local_coordinates(self, position: np.ndarray) -> tuple[float, float]:
        if type(position) is not np.ndarray or position.dtype != np.float64 or position.shape != (2,):
            return super().local_coordinates(position)  # type: ignore[misc]  # the lane's
        key = position.tobytes()  # the exact bits: positions that compare equal but differ (-0.0, 0.0) are two keys
        coordinates = self._memory.get(key)
        if coordinates is None:
            if len(self._memory) >= self.MEMORY:
                self._memory.clear()
            coordinates = self._memory[key] = super().local_coordinates(position)  # type: ignore[misc]  # the lane's
        return coordinates

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_memory": {}}


class RememberingStraightLane(_RememberedCoordinates, StraightLane):
    """highway-env's ``StraightLane`` that remembers the local coordinates of recent positions."""


class RememberingCircularLane(_RememberedCoordinates, CircularLane):
    """highway-env's ``CircularLane`` that remembers the local coordinates of recent positions."""


_REMEMBERING = {StraightLane: RememberingStraightLane, CircularLane: RememberingCircularLane}


def remembering(lane: AbstractLane) -> AbstractLane:
    """
    :param lane: a lane
    :return: a remembering copy of a ``StraightLane`` or ``CircularLane`` (same geometry), any other lane as it is
    """
    remembering_class = _REMEMBERING.get(type(lane))
    if remembering_class is None:
        return lane
    copied = remembering_class.__new__(remembering_class)
    copied.__dict__.update(lane.__dict__)
    copied._memory = {}
    return copied


class IndexedRoadNetwork(RoadNetwork):
    """
    highway-env's ``RoadNetwork`` with a faster ``get_closest_lane_index`` that returns the same lane (see the
    module docstring): lanes whose lower bound exceeds the best distance measured so far are not measured, and ties
    go to the first lane in the network's order, as ``np.argmin`` gives them. Positions or headings that are not
    finite go to highway-env's search.
    """

    CELL = 2.0
    """[m] side of the grid cells whose candidate lanes are remembered."""
    MAX_CELLS = 65536
    """The remembered cells are forgotten when there are this many."""
    _bounds: list[tuple[LaneIndex, AbstractLane, tuple[int, float, float, float, float, float, float]]] | None = None
    _cells: dict[tuple[int, int], list[tuple[float, int]]]

    @classmethod
    def from_network(cls, network: RoadNetwork) -> IndexedRoadNetwork:
        """
        :param network: a road network
        :return: an indexed network of the same lanes (remembering copies of its straight and arc lanes)
        """
        indexed = cls()
        indexed.graph = {
            _from: {_to: [remembering(lane) for lane in lanes] for _to, lanes in to_dict.items()}
            for _from, to_dict in network.graph.items()
        }
        return indexed

    def __getstate__(self) -> dict:
        # The lane bounds and grid cells are rebuilt on demand: a pickled network (a checkpoint's env) stays small.
        return {key: value for key, value in self.__dict__.items() if key not in ("_bounds", "_cells")}

    def add_lane(self, _from: str, _to: str, lane: AbstractLane) -> None:
        super().add_lane(_from, _to, lane)
        self._bounds = None
        self._cells = {}

    def _lane_bounds(self) -> list[tuple[LaneIndex, AbstractLane, tuple[int, float, float, float, float, float, float]]]:
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
        """
        The index of the lane closest to a position (and heading): ``RoadNetwork.get_closest_lane_index``'s answer.

        :param position: a world position [m]
        :param heading: a heading [rad], or ``None`` for the position alone
        :return: the index of the closest lane
        """
        x, y = float(position[0]), float(position[1])
        h = None if heading is None else float(heading)
        if not (math.isfinite(x) and math.isfinite(y) and (h is None or math.isfinite(h))):
            return super().get_closest_lane_index(position, heading)
        lanes = self._lane_bounds()
        cell = (math.floor(x / self.CELL), math.floor(y / self.CELL))
        candidates = self._cells.get(cell)
        if candidates is None:
            candidates = self._cell_candidates(cell)
        best, best_i = math.inf, -1
        for cell_bound, i in candidates:
            if cell_bound > best:
                break  # this lane and the next ones are farther than the best lane, wherever in the cell
            _, lane, (kind, x_min, y_min, x_max, y_max, lane_heading, half_width) = lanes[i]
            if kind != _OTHER:
                dx = x_min - x if x < x_min else (x - x_max if x > x_max else 0.0)
                dy = y_min - y if y < y_min else (y - y_max if y > y_max else 0.0)
                bound = math.hypot(dx, dy)
                if h is not None:
                    angle = abs((h - lane_heading + math.pi) % _TWO_PI - math.pi) - half_width
                    if angle > 0.0:
                        bound = bound + angle if kind == _STRAIGHT else max(bound, angle)
                if bound - _BOUND_TOLERANCE > best:
                    continue
            distance = lane.distance_with_heading(position, heading)
            if distance < best or (distance == best and i < best_i):
                best, best_i = distance, i
        return lanes[best_i][0]

    def _cell_candidates(self, cell: tuple[int, int]) -> list[tuple[float, int]]:
        """
        :param cell: a grid cell (``CELL`` metres square)
        :return: every lane's lower bound over the cell (the distance from the cell to the lane's box; ``-inf``
            for lanes without a bound) and its position in the network's order, nearest first
        """
        if len(self._cells) >= self.MAX_CELLS:
            self._cells.clear()
        x0, y0 = cell[0] * self.CELL, cell[1] * self.CELL
        x1, y1 = x0 + self.CELL, y0 + self.CELL
        candidates = []
        for i, (_, _, (kind, x_min, y_min, x_max, y_max, _, _)) in enumerate(self._lane_bounds()):
            if kind == _OTHER:
                candidates.append((-math.inf, i))
                continue
            dx = max(x_min - x1, x0 - x_max, 0.0)
            dy = max(y_min - y1, y0 - y_max, 0.0)
            candidates.append((math.hypot(dx, dy) - _BOUND_TOLERANCE, i))
        candidates.sort()
        self._cells[cell] = candidates
        return candidates


def _lateral_filter(lane: AbstractLane, margin: float) -> Any:
    """
    A test that rules out, at the cost of a few float operations, positions that ``lane.on_lane(..., margin)``
    rejects for their lateral offset: the offset is computed in Python floats (it may differ from the lane's own in
    the last bits, hence the tolerance) and compared with the half width plus the margin.

    :param lane: a lane
    :param margin: the margin of the ``on_lane`` check [m]
    :return: ``far(position) -> bool``, true only for positions off the lane; ``None`` for lanes of other kinds
    """
    if type(lane) in (StraightLane, RememberingStraightLane):
        (x0, y0), (nx, ny) = lane.start, lane.direction_lateral
        x0, y0, nx, ny = float(x0), float(y0), float(nx), float(ny)
        limit = lane.width / 2 + margin + _BOUND_TOLERANCE
        return lambda position: abs((position[0] - x0) * nx + (position[1] - y0) * ny) > limit
    if type(lane) in (CircularLane, RememberingCircularLane):
        (cx, cy), radius = lane.center, lane.radius
        cx, cy = float(cx), float(cy)
        limit = lane.width / 2 + margin + _BOUND_TOLERANCE
        return lambda position: abs(radius - math.hypot(position[0] - cx, position[1] - cy)) > limit
    return None


def _may_touch(vehicle: Any, other: Any, dt: float) -> bool:
    """
    Whether ``vehicle.handle_collisions(other, dt)`` may do anything: ``False`` only where highway-env's own
    pre-check (centre distance beyond the half diagonals plus the distance ``vehicle`` covers in ``dt``) returns
    at once, found from the larger coordinate difference, which never exceeds the distance.
    """
    if (
        type(vehicle)._is_colliding is not RoadObject._is_colliding
        or type(vehicle).handle_collisions is not RoadObject.handle_collisions
    ):
        return True
    reach = (vehicle.diagonal + other.diagonal) / 2 + vehicle.speed * dt + _BOUND_TOLERANCE
    position, other_position = vehicle.position, other.position
    return abs(other_position[0] - position[0]) <= reach and abs(other_position[1] - position[1]) <= reach


class FastRoad(Road):
    """
    highway-env's ``Road`` with a faster neighbour search and collision loop that give the same answers (see the
    module docstring). Takes ``Road``'s arguments.
    """

    _lane_coordinates: dict[int, list[tuple[Any, float]]] | None = None

    def act(self) -> None:
        """``Road.act()``, with each vehicle's coordinates on each lane queried computed once for all vehicles."""
        self._lane_coordinates = {}
        try:
            super().act()
        finally:
            self._lane_coordinates = None

    def _coordinates_on(self, lane: AbstractLane) -> list[tuple[Any, float]]:
        """
        :param lane: a lane
        :return: the vehicles and objects on it (``on_lane`` with highway-env's 1 m margin) with their longitudinal
            coordinate, in the road's order
        """
        on_lane = []
        far = _lateral_filter(lane, margin=1.0)
        for v in self.vehicles + self.objects:
            if isinstance(v, Landmark) or (far is not None and far(v.position)):
                continue
            s_v, lat_v = lane.local_coordinates(v.position)
            if lane.on_lane(v.position, s_v, lat_v, margin=1):
                on_lane.append((v, s_v))
        return on_lane

    def neighbour_vehicles(self, vehicle: RoadObject, lane_index: LaneIndex | None = None) -> tuple[Any, Any]:
        """
        The vehicles just ahead of and behind a vehicle on a lane: ``Road.neighbour_vehicles``'s answer.

        :param vehicle: the vehicle whose neighbours are searched
        :param lane_index: the lane to search (by default the vehicle's own)
        :return: the preceding vehicle and the following vehicle (``None`` where there is none)
        """
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
        """
        Move every vehicle, then resolve collisions as ``Road.step`` does, in the same order, without the calls
        that return at once because neither object checks collisions.

        :param dt: time step [s]
        """
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
    """
    ``vehicle.predict_trajectory_constant_speed(times)`` without copying the road.

    highway-env's ``Vehicle`` (not its lane-following vehicles) rolls a ``copy.deepcopy`` of itself forward, and the
    copy takes its road along: every vehicle on it. Rolled out detached from the road, the copy moves the same way
    (its kinematics do not read the road; only its closest lane, which the prediction does not return, is skipped).

    :param vehicle: a vehicle
    :param times: the prediction times [s]
    :return: the predicted positions and headings, as highway-env's method returns them
    """
    if type(vehicle).predict_trajectory_constant_speed is not Vehicle.predict_trajectory_constant_speed:
        return vehicle.predict_trajectory_constant_speed(times)
    detached = copy.copy(vehicle)
    # Without the road, the lane (and its remembered coordinates) and the trail, which the roll-out does not read
    detached.road, detached.lane, detached.history, detached.log = None, None, deque(maxlen=vehicle.history.maxlen), []
    return Vehicle.predict_trajectory_constant_speed(detached, times)


class SharedPredictions:
    """
    ``RegulatedRoad`` conflict checks on predictions computed once per vehicle and enforcement; mixed in before a
    ``RegulatedRoad`` (see :class:`FastRegulatedRoad`).
    """

    _predictions: dict[tuple[int, int, float], tuple[np.ndarray, np.ndarray, tuple[float, float, float, float]]] | None = None

    def enforce_road_rules(self) -> None:
        """``RegulatedRoad.enforce_road_rules()``, with each vehicle's predicted trajectory computed once."""
        self._predictions = {}
        try:
            super().enforce_road_rules()  # type: ignore[misc]  # a RegulatedRoad's, after this mixin in the MRO
        finally:
            self._predictions = None

    def _prediction(
        self, vehicle: Vehicle, horizon: int, step: float
    ) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float, float]]:
        key = (id(vehicle), horizon, step)
        assert self._predictions is not None
        prediction = self._predictions.get(key)
        if prediction is None:
            positions, headings = predict_constant_speed(vehicle, np.arange(step, horizon, step))
            points = np.array(positions, dtype=float).reshape(-1, 2)
            box = (*points.min(axis=0), *points.max(axis=0)) if len(points) else (math.inf, math.inf, -math.inf, -math.inf)
            prediction = self._predictions[key] = (points, np.asarray(headings, dtype=float), box)
        return prediction

    def is_conflict_possible(self, v1: Vehicle, v2: Vehicle, horizon: int = 3, step: float = 0.25) -> bool:
        """
        Whether two vehicles may conflict within ``horizon`` seconds: ``RegulatedRoad.is_conflict_possible``'s answer.

        :param v1: a vehicle
        :param v2: another vehicle
        :param horizon: prediction horizon [s]
        :param step: prediction step [s]
        :return: whether their predicted rectangles intersect at some prediction time
        """
        if self._predictions is None:
            return bool(RegulatedRoad.is_conflict_possible(v1, v2, horizon, step))
        points_1, headings_1, box_1 = self._prediction(v1, horizon, step)
        points_2, headings_2, box_2 = self._prediction(v2, horizon, step)
        reach = v1.LENGTH + _BOUND_TOLERANCE
        # No predicted point of one within reach of a point of the other: highway-env's pre-check skips every time.
        if (
            box_2[0] - box_1[2] > reach
            or box_1[0] - box_2[2] > reach
            or box_2[1] - box_1[3] > reach
            or box_1[1] - box_2[3] > reach
        ):
            return False
        count = min(len(points_1), len(points_2))
        gaps = points_2[:count] - points_1[:count]
        # The times that highway-env's pre-check may keep (with a margin for rounding), then its own checks on them.
        for k in np.flatnonzero(np.sqrt(gaps[:, 0] * gaps[:, 0] + gaps[:, 1] * gaps[:, 1]) <= reach):
            if np.linalg.norm(gaps[k]) > v1.LENGTH:
                continue
            if utils.rotated_rectangles_intersect(
                (points_1[k], 1.5 * v1.LENGTH, 0.9 * v1.WIDTH, headings_1[k]),
                (points_2[k], 1.5 * v2.LENGTH, 0.9 * v2.WIDTH, headings_2[k]),
            ):
                return True
        return False


class FastRegulatedRoad(SharedPredictions, RegulatedRoad, FastRoad):
    """highway-env's ``RegulatedRoad`` (junction right of way) on :class:`FastRoad`, with shared conflict predictions."""


def _clip(value: Any, low: float, high: float) -> Any:
    """``np.clip`` of one number (the same value, NaN included), without converting it to an array and back."""
    return low if value < low else (high if value > high else value)


class FastIDMVehicle(IDMVehicle):
    """
    highway-env's ``IDMVehicle``, deciding the same steering and acceleration at less cost.

    ``np.clip`` of a single number converts it to an array and back (microseconds each), and an IDM decision clips
    seven numbers: here the lateral controller (``ControlledVehicle.steering_control``) and the decision (``act``)
    clip Python numbers, which gives the same values, and keep numpy's trigonometric functions (whose results
    differ from the ``math`` module's in the last bit). The IDM acceleration, MOBIL lane changes and the neighbour
    search are highway-env's.
    """

    def steering_control(self, target_lane_index: LaneIndex) -> float:
        """
        The steering angle that follows the centre of a lane: ``ControlledVehicle.steering_control``'s answer
        (lateral offset -> lateral speed -> heading reference ``TAU_PURSUIT`` ahead -> heading rate -> steering).

        :param target_lane_index: the lane to follow
        :return: the steering angle [rad], within ``MAX_STEERING_ANGLE``
        """
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
        """
        The IDM acceleration of a vehicle behind another: ``IDMVehicle.acceleration``'s answer.

        :param ego_vehicle: the vehicle whose acceleration is computed (with this vehicle's IDM parameters)
        :param front_vehicle: the vehicle ahead of it, if any
        :param rear_vehicle: unused, as by highway-env
        :return: the acceleration [m/s²]
        """
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
        """
        ``IDMVehicle.act``'s decision: follow the road, maybe change lane (MOBIL), steer to the target lane and
        accelerate by IDM behind the vehicle ahead (on the target lane too while changing lane), within ``ACC_MAX``.

        :param action: ignored, as by ``IDMVehicle``: the vehicle decides alone
        """
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


def fast_vehicle_class(vehicle_class: type) -> type:
    """
    :param vehicle_class: the traffic's vehicle class (``other_vehicles_type``)
    :return: :class:`FastIDMVehicle` for highway-env's ``IDMVehicle``, any other class as it is
    """
    return FastIDMVehicle if vehicle_class is IDMVehicle else vehicle_class
