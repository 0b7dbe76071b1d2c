"""
Urban intersection of the paper (``DACERF-Intersection-v0``), on highway-env's ``IntersectionEnv``: a four-way
crossroads (one 4 m lane each way, 22 m junction box) with IDM traffic on every arm, the horizontal road having
priority. The ego starts on the south arm 20-40 m before the junction or, with probability
``reference_start_probability`` (0.5; 0 in evaluations: ``IntersectionEnv.EVALUATION_CONFIG``), on its path up to 15 m
into the exit lane, and follows a route drawn among ``routes`` (highway-env's lanes; the U-turn, not drawn by default,
is a keyhole loop through the junction box) at a target speed drawn from ``reference_speed_ranges``. Between the ego
and traffic, ``right_of_way`` ``"first_come"`` lets the one ahead go first; with ``yield_at_junction`` the reference
speed yields at the stop line to crossing traffic until the ego has stopped there
(:meth:`IntersectionEnv.reference_speed_cap`), and an ego that must yield at its start starts no faster than that
yielding speed, from which it can stop at the line. The severe-event
penalty is a constant 500. The episode ends on a collision, off the road, or 25 m into an exit lane (a
success at the route's exit), and is truncated after 40 s.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from highway_env.envs.intersection_env import IntersectionEnv as HighwayIntersectionEnv
from highway_env.road.lane import AbstractLane
from highway_env.road.regulation import RegulatedRoad
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from sb3_dacerf.envs.driving.common import simulation
from sb3_dacerf.envs.driving.common.abstract import PaperDrivingMixin
from sb3_dacerf.envs.driving.common.config import Rule, boolean, choice, interval, number
from sb3_dacerf.envs.driving.common.reference import ReferencePath, nominal_steering
from sb3_dacerf.envs.driving.common.simulation import FastRegulatedRoad

ROUTES = {"straight": 2, "left": 1, "right": 3, "u_turn": 0}  #: route -> exit arm (the ego enters from arm 0)
DEFAULT_ROUTES = ["straight", "left", "right"]  #: the U-turn is hardly drivable at the paper's steering rate
RIGHT_OF_WAY = ("first_come", "priority")

LANE_WIDTH = AbstractLane.DEFAULT_WIDTH
JUNCTION_HALF_SIZE = LANE_WIDTH + 5 + LANE_WIDTH / 2  #: [m] highway-env's ``outer_distance``
U_TURN_RADIUS = 8.5  #: [m] of the U-turn's arcs


def u_turn_points(start: np.ndarray, heading: float, turn_sign: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """
    A keyhole U-turn of arcs of radius ``U_TURN_RADIUS``: a swing away by θ, a loop of π + 2θ towards the turn side
    (``turn_sign``: that of a left turn's heading change), a swing back by θ, ending one lane width to the side.

    :return: positions (N, 2) and headings (N,) every ``step`` metres from ``start``, and at the end of the loop
    """
    theta = np.arccos((U_TURN_RADIUS + LANE_WIDTH / 2) / (2 * U_TURN_RADIUS))
    curvature = turn_sign / U_TURN_RADIUS
    pieces = [(-curvature, theta), (curvature, np.pi + 2 * theta), (-curvature, theta)]
    points, headings = [], []
    position, psi = np.asarray(start, dtype=np.float64), heading
    for kappa, angle in pieces:
        length = angle * U_TURN_RADIUS
        along, end = psi + kappa * np.arange(0.0, length, step), psi + kappa * length
        points.append(position + np.column_stack([np.sin(along) - np.sin(psi), np.cos(psi) - np.cos(along)]) / kappa)
        headings.append(along)
        position, psi = position + np.array([np.sin(end) - np.sin(psi), np.cos(psi) - np.cos(end)]) / kappa, end
    return np.concatenate([*points, [position]]), np.concatenate([*headings, [psi]])


def travel_time(distance: np.ndarray, speed: float, acceleration: float, max_speed: float) -> np.ndarray:
    """
    :return: the time [s] to cover ``distance`` [m] (negative: 0) from ``speed`` >= 0, accelerating at ``acceleration``
        > 0 up to ``max_speed`` [m/s] (the initial speed if it is higher)
    """
    distance = np.maximum(np.asarray(distance, dtype=np.float64), 0.0)
    max_speed = max(max_speed, speed, 1e-6)
    t_accelerating = (max_speed - speed) / acceleration
    d_accelerating = speed * t_accelerating + 0.5 * acceleration * t_accelerating**2
    while_accelerating = (np.sqrt(speed**2 + 2 * acceleration * distance) - speed) / acceleration
    return np.where(distance <= d_accelerating, while_accelerating, t_accelerating + (distance - d_accelerating) / max_speed)


def turn_conflicts(network, ego_exit: int, conflict_distance: float = 3.1, step: float = 0.5) -> dict:
    """
    Where the ego's turn from arm 0 to ``ego_exit`` meets each traffic turn, on their centre lines (each the turn lane
    and the first 10 m of its exit lane, sampled every ``step`` m) within ``conflict_distance`` [m] of each other.

    :return: ``{(a, b): (ego_in, ego_out, traffic_in, traffic_out)}``: for each traffic turn from arm ``a`` (not 0) to
        arm ``b`` that conflicts, the arc lengths [m] from each turn lane's start where the conflict begins and ends
    """

    def path(entry: int, exit_: int) -> np.ndarray:
        turn, exit_lane = network.get_lane((f"ir{entry}", f"il{exit_}", 0)), network.get_lane((f"il{exit_}", f"o{exit_}", 0))
        along = [turn.position(s, 0.0) for s in np.arange(0.0, turn.length, step)]
        return np.array(along + [exit_lane.position(s, 0.0) for s in np.arange(0.0, 10.0, step)])

    ego = path(0, ego_exit)
    conflicts = {}
    for entry in (1, 2, 3):
        for exit_ in [arm for arm in range(4) if arm != entry]:
            other = path(entry, exit_)
            close = np.linalg.norm(ego[:, None] - other[None], axis=-1) < conflict_distance
            ego_index, other_index = np.nonzero(close)
            if len(ego_index):
                ego_in, ego_out, traffic_in, traffic_out = ego_index.min(), ego_index.max(), other_index.min(), other_index.max()
                conflicts[entry, exit_] = (step * ego_in, step * ego_out, step * traffic_in, step * traffic_out)
    return conflicts


def _routes_rule(value: object) -> str | None:
    if isinstance(value, (list, tuple)) and value and all(isinstance(route, str) and route in ROUTES for route in value):
        return None
    return f"a non-empty list of routes among {list(ROUTES)}"


def _speed_ranges_rule(value: object) -> str | None:
    speed_range = interval(0.0, 40.0)
    if isinstance(value, dict) and all(route in ROUTES and speed_range(bounds) is None for route, bounds in value.items()):
        return None
    return f"a dict of route -> [low, high] target speeds [m/s] within [0, 40], routes among {list(ROUTES)}"


class FirstComeRoad(FastRegulatedRoad):
    """The junction road on which a conflict between the ego and traffic goes to the one ahead (traffic: by priority)."""

    @staticmethod
    def respect_priorities(v1: Vehicle, v2: Vehicle) -> Vehicle:
        if isinstance(v1, ControlledVehicle) and isinstance(v2, ControlledVehicle):  # two traffic vehicles
            return RegulatedRoad.respect_priorities(v1, v2)
        return v1 if v1.front_distance_to(v2) > v2.front_distance_to(v1) else v2


class IntersectionEnv(PaperDrivingMixin, HighwayIntersectionEnv):
    """The urban intersection (see the module docstring); takes :class:`PaperDrivingMixin`'s arguments."""

    road: RegulatedRoad
    stopped_at_line: bool  #: the ego has stopped at the stop line in this episode: the reference no longer yields
    DENSITY_CONFIGS: ClassVar[dict[str, dict]] = {
        "sparse": {"initial_vehicle_count": 5, "spawn_probability": 0.03},
        "normal": {"initial_vehicle_count": 10, "spawn_probability": 0.06},
        "dense": {"initial_vehicle_count": 15, "spawn_probability": 0.12},
    }
    CONFIG_RULES: ClassVar[dict[str, Rule]] = {
        "initial_vehicle_count": number(0, integer=True),
        **dict.fromkeys(["spawn_probability", "reference_start_probability"], number(0.0, 1.0)),
        **dict.fromkeys(["clear_crashed_traffic", "yield_at_junction"], boolean()),
        "routes": _routes_rule,
        "reference_speed_ranges": _speed_ranges_rule,
        "right_of_way": choice(RIGHT_OF_WAY),
    }
    EVALUATION_CONFIG: ClassVar[dict] = {"reference_start_probability": 0.0}  #: evaluations start before the junction
    YIELD_DECELERATION = 0.5  #: [m/s²] of the yielding reference's stop at the line
    YIELD_MARGIN = 1.0  #: [s] widening of a traffic vehicle's time window at a conflict
    STOP_ZONE = 2.0  #: [m] before the stop line within which an ego slower than ``STOP_SPEED`` has stopped there
    STOP_SPEED = 0.5  #: [m/s]
    EXIT_DISTANCE = 25.0  #: [m] driven into an exit lane that ends the episode

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(
            {
                "duration": 40,  # [s]
                "initial_vehicle_count": 10,
                "spawn_probability": 0.06,  # per policy step
                "routes": list(DEFAULT_ROUTES),  # the ego's route is drawn uniformly among these (also "u_turn")
                # [m/s] target speed of each route: tight turns are slow, the steering rate is at most 0.25 rad/s
                "reference_speed_ranges": {"straight": [6.0, 9.0], "left": [4.0, 7.0], "right": [3.0, 5.0], "u_turn": [3.0, 4.5]},
                "position_scale": 25.0,
                "speed_scale": 10.0,
                "clear_crashed_traffic": True,  # remove the wrecks of traffic-only crashes
                "right_of_way": "first_come",  # between the ego and traffic: the one ahead goes first; or "priority"
                "yield_at_junction": True,  # the reference speed yields at the stop line; False: the paper's reference
                "collision_penalty": 500.0,  # a constant severe-event penalty (the paper's example: 200)
                # The probability of a start on the reference path (with its curvature's steering) from 20 m before the
                # junction to 10 m before the exit distance: the paper's randomised initial state (evaluations: 0)
                "reference_start_probability": 0.5,
            }
        )
        return config

    def configure(self, config: dict | None) -> None:
        super().configure(config)
        missing = set(self.config["routes"]) - set(self.config["reference_speed_ranges"])
        if missing:
            raise ValueError(f"reference_speed_ranges lacks the route(s) {sorted(missing)} (overrides replace the whole dict)")

    def _make_road(self) -> None:
        """highway-env's junction, on a :class:`FirstComeRoad` (``right_of_way="first_come"``) or a ``FastRegulatedRoad``."""
        super()._make_road()
        first_come = self.config["right_of_way"] == "first_come"
        self.road = simulation.fast_road(self.road, FirstComeRoad if first_come else FastRegulatedRoad)

    def _make_vehicles(self, n_vehicles: int = 10) -> None:
        """Spawn and warm up the traffic as highway-env does, then create the ego, its route and reference."""
        config, rng, network = self.config, self.np_random, self.road.network
        self.stopped_at_line = False
        if not hasattr(self, "_conflicts"):  # the junction is the same in every episode
            self._conflicts = {arm: turn_conflicts(network, arm) for arm in (1, 2, 3)}
        for longitudinal in np.linspace(0, 80, config["initial_vehicle_count"])[:-1]:
            self._spawn_vehicle(longitudinal)
        for _ in range(3 * config["simulation_frequency"]):  # 3 s of traffic so that it is flowing
            self.road.act()
            self.road.step(1 / config["simulation_frequency"])
        self._spawn_vehicle(60, spawn_probability=1.0, go_straight=True, position_deviation=0.1, speed_deviation=0.0)

        self.route = str(rng.choice(config["routes"]))
        exit_arm = ROUTES[self.route]
        approach = network.get_lane(("o0", "ir0", 0))
        exit_lane = network.get_lane((f"il{exit_arm}", f"o{exit_arm}", 0))
        start = approach.length - rng.uniform(20.0, 40.0)
        self.reference_speed = float(rng.uniform(*config["reference_speed_ranges"][self.route]))
        lateral, heading_offset, speed = rng.normal(0.0, 0.2), rng.normal(0.0, 0.02), self._start_speed()
        step = 0.5
        if self.route == "u_turn":
            left = network.get_lane(("ir0", "il1", 0))
            turn_sign = np.sign(left.heading_at(left.length) - left.heading_at(0.0))
            # The loop from 1 m before the junction keeps the ego body 0.9 m or more from the road edges.
            loop = approach.length - 1.0
            points, headings = u_turn_points(approach.position(loop, 0.0), approach.heading_at(loop), turn_sign, step)
            head = ReferencePath.from_lanes([(approach, 0.0, loop)], step)
            tail = ReferencePath.from_lanes(
                [(exit_lane, exit_lane.local_coordinates(points[-1])[0] + step, exit_lane.length)], step
            )
            points = np.concatenate([head.points[:-1], points, tail.points])
            self.reference = ReferencePath(points, np.concatenate([head.headings[:-1], headings, tail.headings]))
        else:
            turn = network.get_lane(("ir0", f"il{exit_arm}", 0))
            self.reference = ReferencePath.from_lanes(
                [(approach, 0.0, approach.length), (turn, 0.0, turn.length), (exit_lane, 0.0, exit_lane.length)], step
            )
        position, heading = approach.position(start, lateral), approach.heading_at(start) + heading_offset
        steering = 0.0
        if config["reference_start_probability"] > 0 and rng.uniform() < config["reference_start_probability"]:
            # Start on the path, with its heading and the steering of its curvature
            end = self.reference.project(exit_lane.position(self.EXIT_DISTANCE - 10.0, 0.0))[0]
            points, headings, curvatures = self.reference.at(np.array([rng.uniform(approach.length - 20.0, end)]))
            normal = np.array([-np.sin(headings[0]), np.cos(headings[0])])
            position, heading = points[0] + lateral * normal, float(headings[0]) + heading_offset
            limit = config["steering_range"]
            steering = min(max(nominal_steering(float(curvatures[0]), self.action_type.vehicle_class.LENGTH), limit[0]), limit[1])
        ego = self.action_type.vehicle_class(self.road, position, heading=heading, speed=speed)
        ego.action["steering"] = steering  # define_spaces() starts the steering command there
        self.controlled_vehicles = [ego]
        self.road.vehicles.append(ego)
        # no collision at the start, as in highway-env
        self.road.vehicles = [v for v in self.road.vehicles if v is ego or np.linalg.norm(v.position - ego.position) >= 20]
        ego.speed = min(ego.speed, self.reference_speed_cap())  # where it must yield, from the yielding speed
        self._note_stop_at_line()

    def front_to_line(self) -> float:
        """[m] from the ego's front to the stop line of its arm, negative past it."""
        ego = self.vehicle
        return float(ego.position[1]) - ego.LENGTH / 2 - JUNCTION_HALF_SIZE

    def _note_stop_at_line(self) -> None:
        """Sets ``stopped_at_line`` once the ego stands at the line: its front within ``STOP_ZONE``, below ``STOP_SPEED``."""
        if -0.5 < self.front_to_line() < self.STOP_ZONE and self.vehicle.speed < self.STOP_SPEED:
            self.stopped_at_line = True

    def reference_speed_cap(self) -> float:
        """
        While the ego must yield, the speed [m/s] from which braking at ``YIELD_DECELERATION`` stops it at the stop
        line (``inf`` otherwise): while its front is before the line (also when it is too fast to stop there, so that
        ignoring the reference does not release it) and a traffic vehicle's time window at a conflict of their paths
        (along its route, arriving no earlier than at 3 m/s² up to 9 m/s, leaving no later than at 2 m/s, widened by
        ``YIELD_MARGIN``) overlaps the ego's (at 0.7 m/s² up to its target speed, its body 3 m before and after the
        conflict). Once the ego has stopped at the line (front within ``STOP_ZONE``, speed below ``STOP_SPEED``) it
        goes first, as at an all-way stop, and the cap is lifted for the rest of the episode: a yielding reference that
        held a standing ego until the traffic left a gap long enough to cross from standstill would hold it for most
        of an episode in normal traffic.
        """
        if not self.config["yield_at_junction"] or self.route == "u_turn" or self.stopped_at_line:
            return np.inf
        ego = self.vehicle
        front_to_line = self.front_to_line()
        if front_to_line <= -0.5:
            return np.inf  # in the junction
        conflicts = self._conflicts[ROUTES[self.route]]
        to_turn = float(ego.position[1]) - JUNCTION_HALF_SIZE  # from the ego's centre to the start of its turn lane
        # the ego's time window at each conflict
        stretches = np.array([(ego_in, ego_out) for ego_in, ego_out, _, _ in conflicts.values()]).reshape(-1, 2)
        padding = np.array([-ego.LENGTH / 2 - 3.0, ego.LENGTH / 2 + 3.0])
        times = travel_time(to_turn + stretches + padding, ego.speed, 0.7, self.reference_speed)
        windows = dict(zip(conflicts, times, strict=True))
        for vehicle in self.road.vehicles:
            if vehicle is ego:
                continue
            lane_index = vehicle.lane_index
            turn = next((lane for lane in (lane_index, *(vehicle.route or ())) if lane[0].startswith("ir")), None)
            if turn is None or (pair := (int(turn[0][2:]), int(turn[1][2:]))) not in conflicts:
                continue
            _, _, traffic_in, traffic_out = conflicts[pair]
            s = vehicle.lane.local_coordinates(vehicle.position)[0]
            if lane_index[0] == turn[0]:
                to_conflict = traffic_in - s
            elif lane_index[1] == turn[0]:
                to_conflict = vehicle.lane.length - s + traffic_in
            else:
                continue
            arrives = float(travel_time(to_conflict - vehicle.LENGTH / 2, vehicle.speed, 3.0, 9.0)) - self.YIELD_MARGIN
            leaves = (to_conflict + traffic_out - traffic_in + vehicle.LENGTH / 2) / max(vehicle.speed, 2.0) + self.YIELD_MARGIN
            if leaves <= 0:
                continue
            enters, exits = windows[pair]
            if enters < leaves and arrives < exits:
                return float(np.sqrt(2 * self.YIELD_DECELERATION * max(front_to_line - 1.0, 0.0)))
        return np.inf

    def _spawn_vehicle(self, longitudinal: float = 0, *args, **kwargs):
        """highway-env's spawner, with its IDM settings for junctions set per vehicle instead of on the class."""
        vehicle = super()._spawn_vehicle(longitudinal, *args, **kwargs)
        if vehicle is not None:
            vehicle.__class__ = simulation.fast_vehicle_class(type(vehicle))  # the same state, faster decisions
            # highway-env's intersection-v0 sets these on the IDMVehicle class, which leaks into every other env.
            vehicle.DISTANCE_WANTED, vehicle.COMFORT_ACC_MAX, vehicle.COMFORT_ACC_MIN = 7.0, 6.0, -3.0
        return vehicle

    def _simulate(self, action: np.ndarray | None = None) -> None:
        super()._simulate(action)
        self._note_stop_at_line()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """The paper's step, then highway-env's intersection traffic update: remove the vehicles that left, spawn new ones."""
        result = super().step(action)
        self._clear_vehicles()
        self._spawn_vehicle(spawn_probability=self.config["spawn_probability"])
        return result

    def _clear_vehicles(self) -> None:
        """highway-env's clean-up of the vehicles that left, and wrecks of traffic-only crashes (``clear_crashed_traffic``)."""
        super()._clear_vehicles()
        if self.config["clear_crashed_traffic"] and not self.vehicle.crashed:
            self.road.vehicles = [v for v in self.road.vehicles if v in self.controlled_vehicles or not v.crashed]

    def _info(self, obs: np.ndarray, action: np.ndarray | None = None) -> dict:
        """The common info, plus the episode's ``route`` (``straight``, ``left``, ``right`` or ``u_turn``)."""
        return {**super()._info(obs, action), "route": self.route}

    def _has_exited(self) -> bool:
        return self.has_arrived(self.vehicle, exit_distance=self.EXIT_DISTANCE)

    def _is_terminated(self) -> bool:
        return super()._is_terminated() or self._has_exited()

    def _is_success(self) -> bool:
        return self._has_exited() and self.vehicle.lane_index[1] == f"o{ROUTES[self.route]}"

    def _road_clearance(self, position: np.ndarray) -> float:
        # Road = the two arms (|x| or |y| within two lane widths of the axis) and the junction box.
        x, y = np.abs(position)
        arm, box = LANE_WIDTH, JUNCTION_HALF_SIZE
        if (x > arm and y > box) or (x > box and y > arm):
            return -float(min(x - arm, y - arm, np.hypot(max(x - box, 0.0), max(y - box, 0.0))))
        return float(min(np.hypot(max(arm - x, 0.0), max(box - y, 0.0)), np.hypot(max(box - x, 0.0), max(arm - y, 0.0))))
