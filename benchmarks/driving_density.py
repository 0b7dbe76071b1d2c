"""
Why a saved driver fails at a traffic density it did not train at: its observation statistics against the vehicle
rows other densities give, and the driver's outcomes with the observation changed one way at a time.

For a driver saved with its ``VecNormalize`` statistics (``examples/models/`` format), it prints

1. per vehicle row (slot) of the observation: the share of training observations that had a vehicle there (the
   statistics' mean of the mask entry) and what an empty row's mask, heading cosine and speed become under the saved
   statistics (after clipping at ``±clip_obs``);
2. per evaluation (density, and how the observation is changed before the policy sees it): the number of vehicles in
   the observation per step, how many entries per step are clipped at ``±clip_obs``, the reference speeds asked for,
   and the outcomes (arrival, collision, off road, distance to the reference path, speed error). The changes:
   ``nearest K`` empties all but the K nearest vehicle rows (the traffic itself is unchanged), ``empty rows zeroed``
   gives empty rows zeros after normalisation (``evaluate_driving.py --zero-empty-rows``).

Usage::

    python benchmarks/driving_density.py examples/models/dacerf_multilane --episodes 20 --seed 77000
    python benchmarks/driving_density.py examples/models/dacerf_multilane --quick     # 3 episodes per row
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from typing import Any

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples"))
from evaluate_driving import evaluate, load_driver  # the examples folder is not a package

from sb3_dacerf.envs.driving.common.observation import vehicle_rows

# (label, density, nearest K vehicle rows kept (None: all), empty rows zeroed after normalisation)
EVALUATIONS = [
    ("sparse", "sparse", None, False),
    ("sparse, empty rows zeroed", "sparse", None, True),
    ("normal", "normal", None, False),
    ("normal, nearest 6", "normal", 6, False),
    ("normal, nearest 4", "normal", 4, False),
    ("normal, nearest 4, empty rows zeroed", "normal", 4, True),
    ("dense", "dense", None, False),
]


def statistics_table(vec_normalize: Any, rows: tuple[int, int, int]) -> str:
    """Per vehicle row: the share of training observations with a vehicle there, and an empty row once normalised."""
    start, count, size = rows
    mean = vec_normalize.obs_rms.mean[start : start + count * size].reshape(count, size)
    empty = vec_normalize.normalize_obs(np.zeros(vec_normalize.observation_space.shape, dtype=np.float32))
    empty = empty[start : start + count * size].reshape(count, size)
    lines = [
        "| vehicle row | training observations with a vehicle there | empty row normalised: mask | heading cosine | speed |",
        "|---|---|---|---|---|",
    ]
    for row in range(count):
        lines.append(f"| {row + 1} | {mean[row, -1]:.1%} | {empty[row, -1]:.1f} | {empty[row, 2]:.1f} | {empty[row, 4]:.1f} |")
    return "\n".join(lines)


def run(driver: Any, density: str, nearest: int | None, zeroed: bool, episodes: int, seed: int) -> dict[str, Any]:
    """One evaluation of the driver with its observation changed as asked, and what its observations looked like."""
    env = gym.make(driver.env_id, density=density, config=driver.config)
    start, count, size = rows = vehicle_rows(env.unwrapped.config)
    clip = driver.vec_normalize.clip_obs
    vehicles, clipped, reference_speeds = [], [], []

    def act(obs: np.ndarray) -> np.ndarray:
        obs = obs.copy()
        table = obs[start : start + count * size].reshape(count, size)
        if nearest is not None:
            table[nearest:] = 0.0
        vehicles.append(int(table[:, -1].sum()))
        normalized = driver.vec_normalize.normalize_obs(obs)
        if zeroed:
            normalized[start : start + count * size].reshape(count, size)[table[:, -1] == 0] = 0.0
        clipped.append(int(np.sum(np.abs(normalized) >= clip - 1e-6)))
        return driver.model.predict(normalized, deterministic=True)[0]

    results = evaluate(act, _RecordingSpeeds(env, reference_speeds), episodes, seed)
    assert rows == vehicle_rows(driver.env.unwrapped.config)
    return {
        **results,
        "vehicles_mean": float(np.mean(vehicles)),
        "vehicles_min": int(np.min(vehicles)),
        "clipped": float(np.mean(clipped)),
        "reference_speed": (float(np.min(reference_speeds)), float(np.mean(reference_speeds)), float(np.max(reference_speeds))),
    }


class _RecordingSpeeds(gym.Wrapper):
    """Keeps the reference speed of every step."""

    def __init__(self, env: gym.Env, speeds: list[float]):
        super().__init__(env)
        self.speeds = speeds

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.speeds.append(info["reference_speed"])
        return obs, reward, terminated, truncated, info


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a saved driver (STEM or STEM.zip) with its metadata and VecNormalize statistics")
    parser.add_argument("--episodes", type=int, default=20, help="episodes per evaluation")
    parser.add_argument("--seed", type=int, default=77_000, help="seed of the first episode of every evaluation")
    parser.add_argument("--quick", action="store_true", help="3 episodes per evaluation")
    parser.add_argument("--torch-threads", type=int, default=1)
    args = parser.parse_args(argv)
    if args.quick:
        args.episodes = 3
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    torch.set_num_threads(args.torch_threads)
    driver = load_driver(args.model)
    if driver.vec_normalize is None:
        sys.exit(f"error: {driver.path} has no VecNormalize statistics beside it: this diagnosis reads them")
    rows = vehicle_rows(driver.env.unwrapped.config)
    started = time.time()
    command = "python benchmarks/driving_density.py " + " ".join(argv if argv is not None else sys.argv[1:])
    print(f"{driver.path} ({driver.env_id}, trained at {driver.density}), statistics {driver.stats_path}\n")
    print(statistics_table(driver.vec_normalize, rows))
    print()
    lines = [
        "| evaluation | vehicles observed per step (mean, min) | entries clipped per step | reference speed (min, mean, max) "
        "| arrival | collision | off road | distance to the reference path | speed error |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, density, nearest, zeroed in EVALUATIONS:
        r = run(driver, density, nearest, zeroed, args.episodes, args.seed)
        low, mean, high = r["reference_speed"]
        lines.append(
            f"| {label} | {r['vehicles_mean']:.1f}, {r['vehicles_min']} | {r['clipped']:.1f} | "
            f"{low:.1f}, {mean:.1f}, {high:.1f} m/s | {r['arrival_rate']:.0%} | {r['collision_rate']:.0%} | "
            f"{r['off_road_rate']:.0%} | {r['lateral_error']:.2f} m | {r['speed_error']:.2f} m/s |"
        )
        print(lines[-1] if len(lines) > 3 else "\n".join(lines), flush=True)
    seeds = f"seeds {args.seed}-{args.seed + args.episodes - 1}"
    machine = platform.processor() or platform.machine()
    print(f"\n{args.episodes} episodes per evaluation ({seeds}), deterministic actions; {machine}, ", end="")
    print(f"torch threads {args.torch_threads}, {time.time() - started:.0f} s\n`{command}`")


if __name__ == "__main__":
    main()
