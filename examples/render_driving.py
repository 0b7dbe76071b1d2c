"""
Render one episode of each driving scenario as a strip of frames saved as a PNG, like the paper's figures:
a lane change on the multi-lane highway and an unprotected left turn at the intersection.

The driver is a trained SB3 / DACERF model given with ``--model`` (``--algo`` picks the class), or by default the
scripted reference tracker :class:`sb3_dacerf.envs.driving.scripted.ScriptedDriver` (pure pursuit on the observed
waypoints, speed control, braking for the vehicle ahead; its yielding to crossing traffic is off here). It reads only
the observation, so its source also shows how the observation is laid out.

Example::

    python examples/render_driving.py --out-dir driving_frames
"""

from __future__ import annotations

import argparse
import os

import gymnasium as gym
import numpy as np

import sb3_dacerf  # noqa: F401  (registers the environment ids)
from sb3_dacerf.envs.driving.scripted import ScriptedDriver

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
        driver = ScriptedDriver(env, yield_to_crossing=False)
        frames, times, done, info = [env.render()], [0.0], False, {}
        while not done:
            action = model.predict(obs, deterministic=True)[0] if model else driver(obs)
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
