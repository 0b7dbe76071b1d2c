"""
The paper's reward and cost terms (DACER-F, its reward / cost table); the reward is the sum of the signed terms,
which ``info["reward_terms"]`` holds. With the pseudo-Huber penalty ``h``: tracking ``-ρ h(error)`` of the lateral,
speed and heading errors; control ``-ρ_acc |a_x|³ - ρ_steer |δ - δ_nom|``; comfort ``-ρ h(rate)`` of the yaw rate,
jerk and steering rate; liveness ``ρ_step clip(v_x, 0, 3) / 3``; safe following ``-ρ_front (1 - tanh(gap / (v_x
Δt_safe)))``; safe space ``-ρ_space Σ intrusion`` into a margin box around the ego (``ρ_side`` / ``ρ_rear`` alongside /
behind); boundary ``-ρ_boundary max(0, W_ego/2 + d_thresh - d)``; and minus the severe-event penalty on a collision,
leaving the road or a stall, which end the episode.
"""

from __future__ import annotations

import math

import numpy as np
from highway_env.vehicle.kinematics import Vehicle

from sb3_dacerf.envs.driving.common.observation import Scene, vehicle_gaps
from sb3_dacerf.envs.driving.common.reference import nominal_steering

REWARD_WEIGHTS = {
    **dict(lat=1.5, long=3.0, heading=0.3, acc=1.0, steer=0.1, yaw=0.7, jerk=0.5, steer_rate=0.005),
    **dict(step=1.0, front=10.0, side=0.0, space=2.0, rear=0.0, boundary=20.0),
}
"""The weights ρ of the terms (config keys ``rho_<name>``), the defaults of both scenarios."""
REWARD_TERMS = tuple(
    "tracking_lateral tracking_speed tracking_heading control_acceleration control_steering comfort_yaw_rate "
    "comfort_jerk comfort_steering_rate liveness safe_front safe_space safe_side safe_rear boundary collision off_road "
    "stalled".split()
)


def pseudo_huber(error: float, delta: float) -> float:
    """Huber-like penalty: quadratic near zero, linear with slope ``delta`` far from it."""
    return delta**2 * (math.sqrt(1.0 + (error / delta) ** 2) - 1.0)


def reward_terms(
    config: dict, scene: Scene, ego: Vehicle, applied_increment: np.ndarray, severe_penalty: float, stalled: bool = False
) -> dict[str, float]:
    """
    The paper's signed reward and cost terms of one step, in the order of ``REWARD_TERMS``, from the env's config,
    the scene after the step, the ego vehicle, the ``[Δa_x, Δδ]`` applied (after clipping), the (positive) penalty of
    a severe event and whether the episode ends for lack of progress (``stall_timeout``).
    """
    huber_delta = config["huber_delta"]
    v_x, _, yaw_rate, acceleration, steering = scene.ego.tolist()
    dt = 1.0 / config["policy_frequency"]
    acceleration_increment, steering_increment = applied_increment.tolist()

    safe_front = safe_space = safe_side = safe_rear = 0.0
    if len(scene.vehicles):
        gap_long, gap_lat, ahead = vehicle_gaps(scene.vehicles, ego.LENGTH, ego.WIDTH)
        if ahead.any():
            gap = max(float(gap_long[ahead].min()), 0.0)
            safe_front = config["rho_front"] * (1 - math.tanh(gap / (max(v_x, 1e-3) * config["safe_time_headway"])))
        margin_long, margin_lat = config["safe_space_margin"]
        # np.minimum / np.maximum: np.clip's values at a fraction of its cost on short arrays
        intrusion = np.minimum(np.maximum(np.minimum(1 - gap_long / margin_long, 1 - gap_lat / margin_lat), 0.0), 1.0)
        if intrusion.any():
            safe_space = config["rho_space"] * float(intrusion.sum())
            safe_side = config["rho_side"] * float(intrusion[gap_long <= 0].sum())
            safe_rear = config["rho_rear"] * float(intrusion[(scene.vehicles[:, 0] < 0) & (gap_long > 0)].sum())

    terms = {
        "tracking_lateral": -config["rho_lat"] * pseudo_huber(scene.lateral_error, huber_delta),
        "tracking_speed": -config["rho_long"] * pseudo_huber(v_x - scene.reference_speed, huber_delta),
        "tracking_heading": -config["rho_heading"] * pseudo_huber(scene.heading_error, huber_delta),
        "control_acceleration": -config["rho_acc"] * abs(acceleration) ** 3,
        "control_steering": -config["rho_steer"] * abs(steering - nominal_steering(scene.reference_curvature, ego.LENGTH)),
        "comfort_yaw_rate": -config["rho_yaw"] * pseudo_huber(yaw_rate, huber_delta),
        "comfort_jerk": -config["rho_jerk"] * pseudo_huber(acceleration_increment / dt, huber_delta),
        "comfort_steering_rate": -config["rho_steer_rate"] * pseudo_huber(steering_increment / dt, huber_delta),
        "liveness": config["rho_step"] * min(max(v_x, 0.0), 3.0) / 3.0,
        "safe_front": -safe_front,
        "safe_space": -safe_space,
        "safe_side": -safe_side,
        "safe_rear": -safe_rear,
        "boundary": -config["rho_boundary"] * max(0.0, ego.WIDTH / 2 + config["boundary_threshold"] - scene.road_clearance),
        "collision": -severe_penalty * float(ego.crashed),
        "off_road": -severe_penalty * float(scene.road_clearance < 0),
        "stalled": -severe_penalty * float(stalled),
    }
    return {name: float(value) for name, value in terms.items()}
