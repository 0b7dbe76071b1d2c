"""
Layer shared by the paper's driving environments, built on highway-env: incremental action,
ego-frame observation, reference path and the paper's reward / cost terms.

The environments subclass highway-env's own ``HighwayEnv`` and ``IntersectionEnv``; this module
replaces their action, observation, reward, termination and info with the paper's task design
(DACER-F, section "Simulation Environment" and the reward / cost table). Units are SI throughout.

Action (``Box`` with the paper's raw increment bounds, ``float32``)
    ``[Δa_x, Δδ]`` with ``Δa_x ∈ [-0.4, 0.25]`` m/s² and ``Δδ ∈ [-0.025, 0.025]`` rad per policy step
    (0.1 s, i.e. jerk in [-4, 2.5] m/s³ and steering rate within ±0.25 rad/s). The increments are
    integrated into the commanded longitudinal acceleration ``a_x ∈ [-0.8, 0.8]`` m/s² and front-wheel
    steering angle ``δ ∈ [-0.571, 0.571]`` rad, which are exactly the ``acceleration`` (m/s²) and
    ``steering`` (front-wheel angle, rad) inputs of highway-env's kinematic bicycle model
    (``highway_env.vehicle.kinematics.Vehicle``). Both start at 0 on ``reset()``. The ego cannot reverse.

Observation (flat ``float32`` vector, ego frame: x along the ego heading, y along highway-env's lateral
axis, i.e. to the driver's right on the rendered image, where world y points down)
    - ego, 5 values: ``[v_x / speed_scale, v_y / speed_scale, r, a_x, δ]``; body-frame velocity of the
      bicycle model (m/s), yaw rate ``r`` (rad/s), commanded ``a_x`` (m/s²) and ``δ`` (rad) unscaled;
    - reference, 4 × W values (W = ``reference_waypoints``, default 10): ``[x / position_scale,
      y / position_scale, cos φ, sin φ]`` for waypoints at the ego's projection on the reference path and
      then every ``reference_waypoint_interval`` (0.5 s) of travel at the target speed, so the spacing
      encodes the target speed; φ is the path heading relative to the ego heading;
    - surrounding vehicles, 6 × M values (M = ``surrounding_vehicles``, default 8), nearest first, within
      ``perception_distance``: ``[x / position_scale, y / position_scale, cos φ, sin φ, v / speed_scale,
      mask]``, relative position of the vehicle centre, relative heading, absolute speed, mask 1;
      padding rows are all zeros (mask 0).

Reward (every signed term is in ``info["reward_terms"]``; their sum is the reward)
    tracking ``-ρ_lat h(e_lat) - ρ_long h(v_x - v_ref) - ρ_φ h(e_φ)``; control ``-ρ_acc |a_x|³ -
    ρ_steer |δ - δ_nom|`` (δ_nom: the bicycle-model steering of the reference curvature); comfort
    ``-ρ_yaw h(r) - ρ_jerk h(Δa_x/Δt) - ρ_Δsteer h(Δδ/Δt)``; liveness ``ρ_step clip(v_x, 0, 3) / 3``;
    safe following ``-ρ_front (1 - tanh(gap / (v_x Δt_safe)))`` for the nearest vehicle in the ego's
    corridor ahead; safe space ``-ρ_space Σ intrusion`` of vehicles into a margin box around the ego body
    (with ``ρ_side`` / ``ρ_rear`` for the parts alongside / behind); boundary ``-ρ_boundary max(0,
    W_ego/2 + d_thresh - d)`` with ``d`` the distance from the ego centre to the road edge (the paper's
    ``d_bound - d_thresh + 1.0`` read as a cost that starts ``d_thresh`` before the body touches the
    edge); ``-collision_penalty`` (200) on collision and on leaving the road, which end the episode.
    ``h(e) = δ_h² (sqrt(1 + (e/δ_h)²) - 1)`` is the pseudo-Huber penalty, ``δ_h = huber_delta`` = 1.
"""

from __future__ import annotations

import math
import os

# Headless machines render offscreen; SDL's "dummy" driver gives black highway-env frames, "offscreen" does not.
if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")

from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402
from highway_env import utils  # noqa: E402
from highway_env.envs.common.abstract import AbstractEnv  # noqa: E402
from highway_env.envs.common.action import ContinuousAction  # noqa: E402
from highway_env.envs.common.observation import ObservationType  # noqa: E402
from highway_env.road.lane import AbstractLane  # noqa: E402

DENSITIES = ("sparse", "normal", "dense")

EGO_FEATURES = 5
WAYPOINT_FEATURES = 4
VEHICLE_FEATURES = 6

REWARD_TERMS = (
    "tracking_lateral",
    "tracking_speed",
    "tracking_heading",
    "control_acceleration",
    "control_steering",
    "comfort_yaw_rate",
    "comfort_jerk",
    "comfort_steering_rate",
    "liveness",
    "safe_front",
    "safe_space",
    "safe_side",
    "safe_rear",
    "boundary",
    "collision",
    "off_road",
)

# highway-env keys that our action / observation / reward replace: dropped so setting them is an error, not a no-op.
_REPLACED_STOCK_KEYS = (
    "observation",
    "action",
    "collision_reward",
    "right_lane_reward",
    "high_speed_reward",
    "lane_change_reward",
    "arrived_reward",
    "reward_speed_range",
    "normalize_reward",
    "offroad_terminal",
    "vehicles_density",
    "ego_spacing",
    "initial_lane_id",
    "controlled_vehicles",
    "destination",
)


def pseudo_huber(error: float, delta: float) -> float:
    """Huber-like penalty: quadratic near zero, linear with slope ``delta`` far from it."""
    return delta**2 * (math.sqrt(1.0 + (error / delta) ** 2) - 1.0)


class ReferencePath:
    """
    A reference path: a polyline sampled from highway-env lanes (or any curve), with arc-length lookups.

    :param points: (N, 2) world positions along the path [m], without repeated points
    :param headings: (N,) path headings at the points [rad]
    """

    def __init__(self, points: np.ndarray, headings: np.ndarray) -> None:
        self.points = np.asarray(points, dtype=np.float64)
        self.headings = np.unwrap(np.asarray(headings, dtype=np.float64))
        segments = np.diff(self.points, axis=0)
        self.s = np.concatenate(([0.0], np.cumsum(np.hypot(segments[:, 0], segments[:, 1]))))
        self.curvatures = np.gradient(self.headings, self.s)
        self._point_list, self._s_list = self.points.tolist(), self.s.tolist()

    @classmethod
    def from_lanes(cls, pieces: list[tuple[AbstractLane, float, float]], step: float) -> ReferencePath:
        """
        Sample consecutive lane pieces along their centre lines.

        :param pieces: ``(lane, start, end)`` longitudinal ranges [m], each piece starting where the last ends
        :param step: sampling interval [m]
        :return: the reference path
        """
        points, headings = [], []
        for i, (lane, start, end) in enumerate(pieces):
            # The last piece keeps its end point; the others leave it to the next piece's start.
            s_values = np.arange(start, end, step)
            if i == len(pieces) - 1:
                s_values = np.append(s_values, end)
            points += [lane.position(s, 0.0) for s in s_values]
            headings += [lane.heading_at(s) for s in s_values]
        return cls(np.array(points), np.array(headings))

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def project(self, position: np.ndarray) -> tuple[float, float]:
        """
        Project a position on the path.

        :param position: world position [m]
        :return: arc length of the foot point [m] and signed lateral offset [m] (highway-env's lane convention)
        """
        offsets = self.points - position
        i = int(np.argmin(np.einsum("ij,ij->i", offsets, offsets)))
        px, py = float(position[0]), float(position[1])
        best = (math.inf, 0.0, 0.0)
        # Scalar math: this runs every step and numpy's per-call cost dominates on 2-vectors.
        for j in (i - 1, i):
            if 0 <= j < len(self.points) - 1:
                (ax, ay), (bx, by) = self._point_list[j], self._point_list[j + 1]
                length = self._s_list[j + 1] - self._s_list[j]
                ux, uy = (bx - ax) / length, (by - ay) / length
                along = min(max((px - ax) * ux + (py - ay) * uy, 0.0), length)
                dx, dy = px - ax - along * ux, py - ay - along * uy
                distance = math.hypot(dx, dy)
                if distance < best[0]:
                    best = (distance, self._s_list[j] + along, ux * dy - uy * dx)
        return best[1], best[2]

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Interpolate the path at arc lengths, extended by straight lines beyond both ends.

        :param s: arc lengths [m], a 1-d array
        :return: positions (K, 2) [m], headings (K,) [rad] and curvatures (K,) [1/m]
        """
        headings = np.interp(s, self.s, self.headings)
        positions = np.empty((len(s), 2))
        positions[:, 0] = np.interp(s, self.s, self.points[:, 0])
        positions[:, 1] = np.interp(s, self.s, self.points[:, 1])
        curvatures = np.interp(s, self.s, self.curvatures)
        if s[0] < 0.0 or s[-1] > self.s[-1]:
            beyond = np.where(s > self.s[-1], s - self.s[-1], np.minimum(s, 0.0))
            positions += beyond[:, None] * np.column_stack([np.cos(headings), np.sin(headings)])
            curvatures[beyond != 0.0] = 0.0
        return positions, headings, curvatures


class IncrementalAction(ContinuousAction):
    """
    Continuous action ``[Δa_x, Δδ]``: increments of the commanded acceleration [m/s²] and front-wheel
    steering angle [rad] of highway-env's kinematic bicycle model, integrated and clipped every policy step.

    The action space is a ``Box`` with the raw increment bounds (SB3 rescales Box bounds itself).

    :param env: the environment
    :param acceleration_increment_range: bounds of Δa_x per policy step [m/s²]
    :param steering_increment_range: bounds of Δδ per policy step [rad]
    :param acceleration_range: bounds of the integrated a_x [m/s²]
    :param steering_range: bounds of the integrated δ [rad]
    """

    def __init__(
        self,
        env: AbstractEnv,
        acceleration_increment_range: tuple[float, float] = (-0.4, 0.25),
        steering_increment_range: tuple[float, float] = (-0.025, 0.025),
        acceleration_range: tuple[float, float] = (-0.8, 0.8),
        steering_range: tuple[float, float] = (-0.571, 0.571),
        **kwargs,
    ) -> None:
        super().__init__(env, acceleration_range=acceleration_range, steering_range=steering_range)
        self.increment_low = np.array([acceleration_increment_range[0], steering_increment_range[0]])
        self.increment_high = np.array([acceleration_increment_range[1], steering_increment_range[1]])
        self.command_low = np.array([acceleration_range[0], steering_range[0]])
        self.command_high = np.array([acceleration_range[1], steering_range[1]])
        self.command = np.zeros(2)  # integrated [a_x, δ]
        self.applied_increment = np.zeros(2)  # increment actually applied after clipping, for the comfort terms

    def space(self) -> spaces.Box:
        return spaces.Box(self.increment_low.astype(np.float32), self.increment_high.astype(np.float32), dtype=np.float32)

    def act(self, action: np.ndarray) -> None:
        increment = np.clip(np.asarray(action, dtype=np.float64), self.increment_low, self.increment_high)
        command = np.clip(self.command + increment, self.command_low, self.command_high)
        self.applied_increment = command - self.command
        self.command = command
        self.controlled_vehicle.act({"acceleration": float(command[0]), "steering": float(command[1])})
        self.last_action = action


class EgoFrameObservation(ObservationType):
    """The paper's flat ego-frame observation; see the module docstring for layout and scaling."""

    def __init__(self, env: AbstractEnv, **kwargs) -> None:
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

    def observe(self) -> np.ndarray:
        scene = self.env.observe_scene()
        vehicles = np.zeros((self.n_vehicles, VEHICLE_FEATURES))
        nearest = scene.vehicles[: self.n_vehicles, :5]
        vehicles[: len(nearest), :5] = nearest
        vehicles[: len(nearest), 5] = 1.0
        obs = np.concatenate([scene.ego, scene.waypoints.ravel(), vehicles.ravel()]) * self.scale
        return obs.astype(np.float32)


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


class PaperDrivingMixin:
    """
    The paper's task layer over a highway-env environment: put it first in the bases of a subclass of a
    highway-env environment, which must build ``self.reference`` (a :class:`ReferencePath`) and
    ``self.reference_speed`` when it creates the ego vehicle, and implement ``_road_clearance`` and
    ``_is_success``.

    :param config: overrides of ``default_config()``; unknown keys raise ``ValueError``
    :param render_mode: ``None``, ``"rgb_array"`` or ``"human"``
    :param density: traffic density, one of ``"sparse"``, ``"normal"``, ``"dense"``
    """

    DENSITY_CONFIGS: dict[str, dict] = {}
    """Config overrides of each traffic density."""

    reference: ReferencePath
    reference_speed: float

    def __init__(self, config: dict | None = None, render_mode: str | None = None, density: str = "normal") -> None:
        if density not in DENSITIES:
            raise ValueError(f"Unknown density {density!r}: expected one of {', '.join(map(repr, DENSITIES))}")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"Unknown render_mode {render_mode!r}: expected None or one of {self.metadata['render_modes']}")
        if config is not None and not isinstance(config, dict):
            raise TypeError(f"config must be a dict of overrides, got {type(config).__name__}")
        self.density = density
        self._reward_terms = dict.fromkeys(REWARD_TERMS, 0.0)
        self.scene: Scene | None = None
        super().__init__({**self.DENSITY_CONFIGS[density], **(config or {})}, render_mode=render_mode)

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
                "rho_lat": 1.5,
                "rho_long": 3.0,
                "rho_heading": 0.3,
                "rho_acc": 1.0,
                "rho_steer": 0.1,
                "rho_yaw": 0.7,
                "rho_jerk": 0.5,
                "rho_steer_rate": 0.005,
                "rho_step": 1.0,
                "rho_front": 10.0,
                "rho_side": 0.0,
                "rho_space": 2.0,
                "rho_rear": 0.0,
                "rho_boundary": 20.0,
                "safe_time_headway": 1.0,  # Δt_safe [s]
                "safe_space_margin": [3.0, 1.0],  # [m] longitudinal, lateral clearance around the ego body
                "boundary_threshold": 0.5,  # d_thresh [m]
                "collision_penalty": 200.0,
            }
        )
        return config

    def configure(self, config: dict | None) -> None:
        unknown = sorted(set(config or {}) - set(self.default_config()))
        if unknown:
            raise ValueError(
                f"Unknown config key(s) {unknown} for {type(self).__name__}; valid keys: {sorted(self.default_config())}"
            )
        super().configure(config)

    def define_spaces(self) -> None:
        config = self.config
        self.observation_type = EgoFrameObservation(self)
        self.action_type = IncrementalAction(
            self,
            acceleration_increment_range=config["acceleration_increment_range"],
            steering_increment_range=config["steering_increment_range"],
            acceleration_range=config["acceleration_range"],
            steering_range=config["steering_range"],
        )
        # highway-env rebuilds the spaces on every reset; keeping ours keeps any seed set on them.
        if self.observation_space is None or self.observation_space.shape != self.observation_type.space().shape:
            self.observation_space = self.observation_type.space()
        if self.action_space is None or self.action_space != self.action_type.space():
            self.action_space = self.action_type.space()

    def _reset(self) -> None:
        self._reward_terms = dict.fromkeys(REWARD_TERMS, 0.0)
        super()._reset()
        # The ego stops instead of reversing: the paper's task has no reverse gear.
        self.vehicle.MIN_SPEED = 0.0

    def _is_truncated(self) -> bool:
        # highway-env accumulates time in steps of 1 / policy_frequency: compare with a tolerance.
        return self.time >= self.config["duration"] - 1e-6

    def _start_speed(self) -> float:
        """
        Initial ego speed [m/s]: ``self.reference_speed`` ± 0.5 m/s (normal noise), never negative.

        Both scenarios start the ego near its target speed: started far from it (the multilane once drew it like
        the traffic's, up to 10 m/s off, with ±0.8 m/s² to close the gap), the speed-tracking cost alone averaged
        ~250 per episode even for an ideal driver, and leaving the road (-200) was the better return in ~30% of them.
        """
        return max(self.reference_speed + self.np_random.normal(0.0, 0.5), 0.0)

    def _road_clearance(self, position: np.ndarray) -> float:
        """Distance [m] from a position to the nearest road edge, negative off the road."""
        raise NotImplementedError

    def _is_success(self) -> bool:
        """Whether the episode's task is achieved (route completed / destination reached)."""
        raise NotImplementedError

    def observe_scene(self) -> Scene:
        """Compute (and keep in ``self.scene``) what the ego perceives, for the observation and the reward."""
        config = self.config
        ego = self.vehicle
        beta = math.atan(0.5 * math.tan(ego.action["steering"]))
        ego_state = np.array(
            [
                ego.speed * math.cos(beta),
                ego.speed * math.sin(beta),
                ego.speed * math.sin(beta) / (ego.LENGTH / 2),  # heading rate of the bicycle model
                *self.action_type.command,
            ]
        )
        cos_h, sin_h = math.cos(ego.heading), math.sin(ego.heading)
        to_ego_frame_t = np.array([[cos_h, -sin_h], [sin_h, cos_h]])

        s, lateral = self.reference.project(ego.position)
        step = self.reference_speed * config["reference_waypoint_interval"]
        points, headings, curvatures = self.reference.at(s + step * np.arange(config["reference_waypoints"]))
        relative_headings = headings - ego.heading
        waypoints = np.empty((len(points), WAYPOINT_FEATURES))
        waypoints[:, :2] = (points - ego.position) @ to_ego_frame_t
        waypoints[:, 2], waypoints[:, 3] = np.cos(relative_headings), np.sin(relative_headings)

        vehicles = np.zeros((0, 7))
        others = [v for v in self.road.vehicles if v is not ego]
        if others:
            # One array of [x, y, heading, speed, length, width] per vehicle, then vectorised.
            data = np.array([(*v.position, v.heading, v.speed, v.LENGTH, v.WIDTH) for v in others])
            data[:, :2] -= ego.position
            distances = np.hypot(data[:, 0], data[:, 1])
            visible = np.flatnonzero(distances < config["perception_distance"])
            data = data[visible[np.argsort(distances[visible], kind="stable")]]
            relative = data[:, 2] - ego.heading
            vehicles = np.empty((len(data), 7))
            vehicles[:, :2] = data[:, :2] @ to_ego_frame_t
            vehicles[:, 2], vehicles[:, 3], vehicles[:, 4:] = np.cos(relative), np.sin(relative), data[:, 3:]
        self.scene = Scene(
            ego=ego_state,
            waypoints=waypoints,
            vehicles=vehicles,
            lateral_error=lateral,
            heading_error=float(utils.wrap_to_pi(ego.heading - float(headings[0]))),
            reference_curvature=float(curvatures[0]),
            road_clearance=self._road_clearance(ego.position),
        )
        return self.scene

    def _rewards(self, action: np.ndarray | None = None) -> dict[str, float]:
        """
        The paper's signed reward and cost terms at the current state (``observe_scene`` must have run).

        :param action: unused: the increments that count are those applied after clipping
        :return: a dict of {term: signed contribution to the reward}
        """
        config, scene, ego = self.config, self.scene, self.vehicle
        huber_delta = config["huber_delta"]
        v_x, _, yaw_rate, acceleration, steering = scene.ego.tolist()
        dt = 1.0 / config["policy_frequency"]
        beta_nominal = math.asin(min(max(scene.reference_curvature * ego.LENGTH / 2, -1.0), 1.0))
        steering_nominal = math.atan(2.0 * math.tan(beta_nominal))
        acceleration_increment, steering_increment = self.action_type.applied_increment.tolist()

        safe_front = safe_space = safe_side = safe_rear = 0.0
        if len(scene.vehicles):
            x, y, lengths, widths = scene.vehicles[:, 0], scene.vehicles[:, 1], scene.vehicles[:, 5], scene.vehicles[:, 6]
            gap_long = np.abs(x) - (ego.LENGTH + lengths) / 2
            gap_lat = np.abs(y) - (ego.WIDTH + widths) / 2
            ahead = (x > 0) & (gap_lat < 0)  # vehicles in the ego's corridor ahead
            if ahead.any():
                gap = max(float(gap_long[ahead].min()), 0.0)
                safe_front = config["rho_front"] * (1 - math.tanh(gap / (max(v_x, 1e-3) * config["safe_time_headway"])))
            margin_long, margin_lat = config["safe_space_margin"]
            intrusion = np.clip(np.minimum(1 - gap_long / margin_long, 1 - gap_lat / margin_lat), 0.0, 1.0)
            if intrusion.any():
                safe_space = config["rho_space"] * float(intrusion.sum())
                safe_side = config["rho_side"] * float(intrusion[gap_long <= 0].sum())
                safe_rear = config["rho_rear"] * float(intrusion[(x < 0) & (gap_long > 0)].sum())

        off_road = scene.road_clearance < 0
        return {
            "tracking_lateral": -config["rho_lat"] * pseudo_huber(scene.lateral_error, huber_delta),
            "tracking_speed": -config["rho_long"] * pseudo_huber(v_x - self.reference_speed, huber_delta),
            "tracking_heading": -config["rho_heading"] * pseudo_huber(scene.heading_error, huber_delta),
            "control_acceleration": -config["rho_acc"] * abs(acceleration) ** 3,
            "control_steering": -config["rho_steer"] * abs(steering - steering_nominal),
            "comfort_yaw_rate": -config["rho_yaw"] * pseudo_huber(yaw_rate, huber_delta),
            "comfort_jerk": -config["rho_jerk"] * pseudo_huber(acceleration_increment / dt, huber_delta),
            "comfort_steering_rate": -config["rho_steer_rate"] * pseudo_huber(steering_increment / dt, huber_delta),
            "liveness": config["rho_step"] * min(max(v_x, 0.0), 3.0) / 3.0,
            "safe_front": -safe_front,
            "safe_space": -safe_space,
            "safe_side": -safe_side,
            "safe_rear": -safe_rear,
            "boundary": -config["rho_boundary"] * max(0.0, ego.WIDTH / 2 + config["boundary_threshold"] - scene.road_clearance),
            "collision": -config["collision_penalty"] * float(ego.crashed),
            "off_road": -config["collision_penalty"] * float(off_road),
        }

    def _reward(self, action: np.ndarray) -> float:
        self._reward_terms = {name: float(value) for name, value in self._rewards(action).items()}
        return float(sum(self._reward_terms.values()))

    def _is_terminated(self) -> bool:
        """Collisions and leaving the road end the episode."""
        return bool(self.vehicle.crashed or self.scene.road_clearance < 0)

    def _info(self, obs: np.ndarray, action: np.ndarray | None = None) -> dict:
        crashed, off_road = bool(self.vehicle.crashed), bool(self.scene.road_clearance < 0)
        return {
            "speed": float(self.vehicle.speed),
            "reference_speed": float(self.reference_speed),
            "crashed": crashed,
            "collision": crashed,
            "off_road": off_road,
            "is_success": bool(self._is_success() and not (crashed or off_road)),
            "reward_terms": dict(self._reward_terms),
        }
