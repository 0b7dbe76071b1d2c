"""
Render one episode of each driving scenario as a strip of frames saved as a PNG, like the paper's figures:
a lane change on the multi-lane highway and an unprotected left turn at the intersection.

The driver is a trained SB3 / DACERF model given with ``--model`` (``--algo`` picks the class), or by default a
scripted reference tracker written for this example (pure pursuit on the observed waypoints, speed control,
braking for the vehicle ahead). It reads only the observation, so it also shows how the observation is laid out.

Example::

    python examples/render_driving.py --out-dir driving_frames
"""

from __future__ import annotations

import argparse
import os

import gymnasium as gym
import numpy as np

import sb3_dacerf  # noqa: F401  (registers the environment ids)
from sb3_dacerf.envs.driving.common import EGO_FEATURES, VEHICLE_FEATURES, WAYPOINT_FEATURES

SCENARIOS = {
    # Seeds picked where the scripted tracker completes the manoeuvre; frame times [s] (None: spread over the episode).
    "DACERF-Multilane-v0": {
        "config": {"reference_lane": "left", "duration": 6},
        "seed": 0,
        "name": "lane_change",
        "times": [0.0, 0.8, 1.6, 2.4, 4.0],
    },
    "DACERF-Intersection-v0": {"config": {"routes": ["left"]}, "seed": 5, "name": "left_turn", "times": None},
}


def scripted_action(obs: np.ndarray, env: gym.Env) -> np.ndarray:
    """
    Track the reference with pure pursuit and a speed controller, braking for the vehicle in the corridor ahead.

    :param obs: the flat observation
    :param env: the environment (for its config scales, action bounds and ego dimensions)
    :return: the increments [Δa_x, Δδ]
    """
    unwrapped = env.unwrapped
    config = unwrapped.config
    position_scale, speed_scale = config["position_scale"], config["speed_scale"]
    n_waypoints = config["reference_waypoints"]
    v_x, _, _, acceleration, steering = obs[:EGO_FEATURES] * np.array([speed_scale, speed_scale, 1, 1, 1])
    waypoints = obs[EGO_FEATURES : EGO_FEATURES + WAYPOINT_FEATURES * n_waypoints].reshape(-1, 4) * position_scale
    vehicles = obs[EGO_FEATURES + WAYPOINT_FEATURES * n_waypoints :].reshape(-1, VEHICLE_FEATURES)

    # The waypoint spacing is the target speed times the waypoint interval.
    reference_speed = np.hypot(*(waypoints[1, :2] - waypoints[0, :2])) / config["reference_waypoint_interval"]
    half_length = unwrapped.vehicle.LENGTH / 2
    # Look ahead ~0.8 s of travel, at least 4 m, along the waypoints.
    distances = np.hypot(waypoints[:, 0], waypoints[:, 1])
    target = waypoints[min(int(np.searchsorted(distances, max(4.0, 0.8 * v_x))), n_waypoints - 1), :2]
    curvature = 2 * target[1] / max(target @ target, 1e-6)
    desired_steering = np.arctan(2 * np.tan(np.arcsin(np.clip(curvature * half_length, -1, 1))))
    desired_acceleration = 0.5 * (reference_speed - v_x)
    for x, y, _, _, _, mask in vehicles:
        gap = x * position_scale - unwrapped.vehicle.LENGTH
        if mask and x > 0 and abs(y * position_scale) < 2.5 and gap < 2.0 * max(v_x, 1.0) + 5:
            desired_acceleration = -1.0
    increment = np.array([desired_acceleration - acceleration, desired_steering - steering])
    return np.clip(increment, env.action_space.low, env.action_space.high).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out-dir", default="driving_frames", help="folder of the PNG strips")
    parser.add_argument("--frames", type=int, default=5, help="frames per strip, spread over the episode")
    parser.add_argument("--model", help="path of a trained model .zip (default: the scripted tracker)")
    parser.add_argument("--algo", default="dacerf", choices=["dacerf", "sac"], help="class of --model")
    args = parser.parse_args()

    from PIL import Image

    model = None
    if args.model:
        if args.algo == "dacerf":
            from sb3_dacerf import DACERF as algo_class
        else:
            from stable_baselines3 import SAC as algo_class
        model = algo_class.load(args.model)

    os.makedirs(args.out_dir, exist_ok=True)
    for env_id, scenario in SCENARIOS.items():
        env = gym.make(env_id, render_mode="rgb_array", config=scenario["config"])
        obs, _ = env.reset(seed=scenario["seed"])
        frames, times, done, info = [env.render()], [0.0], False, {}
        while not done:
            action = model.predict(obs, deterministic=True)[0] if model else scripted_action(obs, env)
            obs, _, terminated, truncated, info = env.step(action)
            frames.append(env.render())
            times.append(env.unwrapped.time)
            done = terminated or truncated
        if scenario["times"] and not args.model:
            picks = np.searchsorted(np.round(times, 6), scenario["times"]).clip(0, len(frames) - 1)
        else:
            picks = np.linspace(0, len(frames) - 1, args.frames).round().astype(int)
        strip = np.concatenate([frames[i] for i in picks], axis=1)
        path = os.path.join(args.out_dir, f"{scenario['name']}.png")
        Image.fromarray(strip).save(path)
        print(
            f"{env_id}: {len(frames) - 1} steps, success={info['is_success']}, collision={info['collision']}, "
            f"frames at t = {', '.join(f'{times[i]:.1f}' for i in picks)} s -> {path}"
        )
        env.close()


if __name__ == "__main__":
    main()
