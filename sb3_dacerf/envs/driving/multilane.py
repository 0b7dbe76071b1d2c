"""
Multi-lane highway of the paper (``DACERF-Multilane-v0``), on highway-env's ``HighwayEnv``: ``lanes_count`` lanes of
IDM / MOBIL traffic that changes lanes and cuts in (only the ego's collisions are checked). The reference is the
centre line of the ego's lane or of an adjacent one, at a target speed drawn from ``reference_speed_range``. Only
``traffic_window`` around the ego is simulated: vehicles leaving it re-enter at the other end, keeping
``vehicles_count``. The episode ends on a collision or off the road, and is truncated (a success) after ``duration``.
"""

from __future__ import annotations

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


class MultilaneEnv(PaperDrivingMixin, HighwayEnv):
    """The multi-lane highway (see the module docstring); takes :class:`PaperDrivingMixin`'s arguments."""

    road: Road
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
        reference_lane_id = ego_lane_id + int(rng.choice([o for o in offsets if 0 <= ego_lane_id + o < lanes_count]))

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
