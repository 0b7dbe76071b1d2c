"""
Multi-lane highway of the paper (``DACERF-Multilane-v0``), on highway-env's ``HighwayEnv``: ``lanes_count`` lanes of
IDM / MOBIL traffic that changes lanes and cuts in (only the ego's collisions are checked), placed in a steady flow
(each vehicle no faster than it can follow the one ahead). The reference is the centre line of the ego's lane or of an
adjacent one, at a target speed drawn from ``reference_speed_range`` and capped by the vehicle ahead
(:meth:`MultilaneEnv.reference_speed_cap`). Only ``traffic_window`` around the ego is simulated: vehicles leaving it
re-enter at the other end, keeping ``vehicles_count``. The episode ends on a collision or off the road, and is
truncated (a success) after ``duration``.
"""

from __future__ import annotations

import itertools
import math
from typing import ClassVar

import numpy as np
from highway_env import utils
from highway_env.envs.highway_env import HighwayEnv
from highway_env.road.lane import AbstractLane
from highway_env.road.road import LaneIndex, Road
from highway_env.vehicle.kinematics import Vehicle

from sb3_dacerf.envs.driving.common import simulation
from sb3_dacerf.envs.driving.common.abstract import PaperDrivingMixin
from sb3_dacerf.envs.driving.common.config import Rule, choice, interval, number
from sb3_dacerf.envs.driving.common.reference import ReferencePath

REFERENCE_LANES = ("random", "current", "left", "right")


def idm_steady_speed(follower: Vehicle, leader: Vehicle) -> float:
    """
    The highest speed [m/s], up to the follower's, at which an IDM follower's acceleration behind ``leader`` (same
    straight lane) is not negative: the traffic starts in a steady flow instead of braking hard at once.
    """
    speed = follower.speed
    if not hasattr(follower, "desired_gap"):
        return speed
    distance, leader_speed = leader.position[0] - follower.position[0], leader.speed
    target_speed = max(getattr(follower, "target_speed", speed), 1e-3)
    comfort = math.sqrt(-follower.COMFORT_ACC_MAX * follower.COMFORT_ACC_MIN)

    def accelerates(v: float) -> bool:
        desired_gap = follower.DISTANCE_WANTED + v * follower.TIME_WANTED + v * (v - leader_speed) / (2 * comfort)
        return 1.0 - (v / target_speed) ** follower.DELTA - (max(desired_gap, 0.0) / distance) ** 2 >= 0.0

    if accelerates(speed):
        return speed
    low, high = 0.0, speed
    for _ in range(30):  # bisection: the acceleration falls with the speed
        middle = (low + high) / 2
        low, high = (middle, high) if accelerates(middle) else (low, middle)
    return low


class MultilaneEnv(PaperDrivingMixin, HighwayEnv):
    """The multi-lane highway (see the module docstring); takes :class:`PaperDrivingMixin`'s arguments."""

    road: Road
    reference_lane_id: int  #: the lane of the ego's reference path
    DENSITY_CONFIGS: ClassVar[dict[str, dict]] = {
        "sparse": {"vehicles_count": 6},
        "normal": {"vehicles_count": 12},
        "dense": {"vehicles_count": 20},
    }
    CONFIG_RULES: ClassVar[dict[str, Rule]] = {
        "lanes_count": number(1, integer=True),
        "vehicles_count": number(0, integer=True),
        "traffic_window": interval(contains_zero=True),
        "traffic_speed_range": interval(0.0, Vehicle.MAX_SPEED),
        "reference_speed_range": interval(0.0, Vehicle.MAX_SPEED),
        "reference_lane": choice(REFERENCE_LANES),
    }
    TRAFFIC_GAP = 15.0  #: [m] at least between the centres of two vehicles placed in the same lane
    EGO_CLEARANCE = (-20.0, 30.0)  #: [m] behind and ahead of the ego in its lane where no vehicle is placed

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(
            {
                "lanes_count": 3,
                "vehicles_count": 12,
                "traffic_window": [-80.0, 120.0],  # [m] simulated stretch around the ego
                "traffic_speed_range": [20.0, 25.0],  # [m/s] initial and desired speeds of the traffic
                "reference_speed_range": [15.0, 25.0],  # [m/s] target speed of the ego
                "reference_lane": "random",  # "random" (current or adjacent), "current", "left" or "right"
            }
        )
        return config

    def configure(self, config: dict | None) -> None:
        super().configure(config)
        if self.config["lanes_count"] < 2 and self.config["reference_lane"] in ("left", "right"):
            raise ValueError("reference_lane 'left' / 'right' needs lanes_count >= 2")

    def _create_road(self) -> None:
        """highway-env's straight multi-lane road, on the faster classes of :mod:`.simulation`."""
        super()._create_road()
        self.road = simulation.fast_road(self.road)

    def _create_vehicles(self) -> None:
        """Create the ego near its reference speed, its reference lane, and the traffic around it."""
        config, rng, network = self.config, self.np_random, self.road.network
        lanes_count = config["lanes_count"]
        offsets = {"random": (-1, 0, 1), "current": (0,), "left": (-1,), "right": (1,)}[config["reference_lane"]]
        ego_lanes = [i for i in range(lanes_count) if any(0 <= i + o < lanes_count for o in offsets)]
        ego_lane_id = int(rng.choice(ego_lanes))
        lane_offsets = [o for o in offsets if 0 <= ego_lane_id + o < lanes_count]
        self.reference_lane_id = reference_lane_id = ego_lane_id + int(rng.choice(lane_offsets))

        ego_lane = network.get_lane(("0", "1", ego_lane_id))
        x0 = 20.0 - config["traffic_window"][0]
        self.reference_speed = float(rng.uniform(*config["reference_speed_range"]))
        position, heading = ego_lane.position(x0, rng.normal(0.0, 0.2)), ego_lane.heading_at(x0) + rng.normal(0.0, 0.01)
        ego = self.action_type.vehicle_class(self.road, position, heading=heading, speed=self._start_speed())
        self.controlled_vehicles = [ego]
        self.road.vehicles.append(ego)

        reference_lane = network.get_lane(("0", "1", reference_lane_id))
        end = x0 + Vehicle.MAX_SPEED * config["duration"] + 100.0
        self.reference = ReferencePath.from_lanes([(reference_lane, x0 - 50.0, end)], step=10.0)

        behind, ahead = config["traffic_window"]
        self._pending_entries: list[bool] = []  # vehicles to re-enter: True ahead of the ego, False behind
        for _ in range(config["vehicles_count"]):
            self._place_traffic_vehicle(x0 + behind, x0 + ahead)
        # Front to back in each lane, every vehicle starts no faster than it can follow the one ahead of it; twice, as the
        # ego's cap also reads its reference lane.
        lanes: dict[LaneIndex, list[Vehicle]] = {}
        for vehicle in self.road.vehicles:
            lanes.setdefault(vehicle.lane_index, []).append(vehicle)
        for _ in range(2):
            ego.speed = min(ego.speed, self.reference_speed_cap())
            for vehicles in lanes.values():
                vehicles.sort(key=lambda v: -v.position[0])
                for leader, follower in itertools.pairwise(vehicles):
                    if follower is not ego:
                        follower.speed = min(follower.speed, idm_steady_speed(follower, leader))
        ego.speed = min(ego.speed, self.reference_speed_cap())

    def reference_speed_cap(self) -> float:
        """
        The speed [m/s] from which braking at the ego's limit (``acceleration_range``) brings it to the speed of the
        nearest traffic vehicle ahead in its lane or its reference lane at ``safe_time_headway`` behind it; closer
        than that, as much below the leader's speed as it would be above it as far beyond (the gap is restored).
        ``inf`` with no vehicle ahead within ``perception_distance``.
        """
        ego, config = self.vehicle, self.config
        lanes = {ego.lane_index[2], self.reference_lane_id}
        ahead = [
            v
            for v in self.road.vehicles
            if v is not ego and v.lane_index[2] in lanes and 0.0 < v.position[0] - ego.position[0] < config["perception_distance"]
        ]
        if not ahead:
            return np.inf
        leader = min(ahead, key=lambda v: v.position[0])
        gap = leader.position[0] - ego.position[0] - (ego.LENGTH + leader.LENGTH) / 2
        slack = gap - leader.speed * config["safe_time_headway"]
        return max(leader.speed + math.copysign(math.sqrt(2.0 * -config["acceleration_range"][0] * abs(slack)), slack), 0.0)

    def _place_traffic_vehicle(self, low: float, high: float) -> bool:
        """:return: whether a traffic vehicle was put at a random free spot of a random lane between two abscissas [m]"""
        config, rng = self.config, self.np_random
        vehicle_type = simulation.fast_vehicle_class(utils.class_from_path(config["other_vehicles_type"]))
        ego_x, ego_lane = self.vehicle.position[0], self.vehicle.lane_index
        abscissas: dict[LaneIndex, list[float]] = {}  # of the vehicles on each lane, gathered once for the 50 draws
        for v in self.road.vehicles:
            abscissas.setdefault(v.lane_index, []).append(v.position[0])
        for _ in range(50):
            lane_index: LaneIndex = ("0", "1", int(rng.integers(config["lanes_count"])))
            x = rng.uniform(low, high)
            if (
                (lane_index == ego_lane and self.EGO_CLEARANCE[0] < x - ego_x < self.EGO_CLEARANCE[1])
                or abs(x - ego_x) < self.TRAFFIC_GAP  # nobody alongside the ego either
                or any(abs(v_x - x) < self.TRAFFIC_GAP for v_x in abscissas.get(lane_index, ()))
            ):
                continue
            vehicle = vehicle_type.make_on_lane(self.road, lane_index, x, speed=rng.uniform(*config["traffic_speed_range"]))
            vehicle.randomize_behavior()
            ahead = [v for v in self.road.vehicles if v.lane_index == lane_index and v.position[0] > x]
            if ahead:
                vehicle.speed = min(vehicle.speed, idm_steady_speed(vehicle, min(ahead, key=lambda v: v.position[0])))
            vehicle.check_collisions = False  # only the ego's collisions matter, as in highway-fast-v0
            self.road.vehicles.append(vehicle)
            return True
        return False

    def _simulate(self, action: np.ndarray | None = None) -> None:
        """Step the traffic, then move the vehicles that left the simulated window to its other end."""
        super()._simulate(action)
        behind, ahead = self.config["traffic_window"]
        ego_x = self.vehicle.position[0]
        for vehicle in [v for v in self.road.vehicles if v is not self.vehicle]:
            dx = vehicle.position[0] - ego_x
            if dx < behind or dx > ahead:
                self.road.vehicles.remove(vehicle)
                self._pending_entries.append(dx < behind)
        # Entries that find no free spot wait for a later step, so the vehicle count stays constant.
        windows = {True: (ego_x + ahead - 20.0, ego_x + ahead), False: (ego_x + behind, ego_x + behind + 20.0)}
        self._pending_entries = [front for front in self._pending_entries if not self._place_traffic_vehicle(*windows[front])]

    def _road_clearance(self, position: np.ndarray) -> float:
        lane_width = AbstractLane.DEFAULT_WIDTH
        lateral = self.road.network.get_lane(("0", "1", 0)).local_coordinates(position)[1]
        return float(min(lateral + lane_width / 2, (self.config["lanes_count"] - 0.5) * lane_width - lateral))

    def _is_success(self) -> bool:
        """The drive is completed when the time limit is reached."""
        return self._is_truncated()
