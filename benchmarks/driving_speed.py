"""
Environment steps per second of the driving scenarios on this package's simulation classes
(:mod:`sb3_dacerf.envs.driving.common.simulation`) and on highway-env's own, side by side in one process: normal
density, seeded resets and one fixed action sequence (resets included in the time). The two must give identical
episodes (observations, rewards and flags); the script exits with an error otherwise.

    python benchmarks/driving_speed.py [--steps 1000] [--repeats 2]
"""

import argparse
import contextlib
import platform
import sys
import time
from unittest import mock

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import gymnasium as gym
import highway_env
import numpy as np
from highway_env.road.regulation import RegulatedRoad

import sb3_dacerf  # noqa: F401  (registers the ids)
from sb3_dacerf.envs.driving.common import simulation
from sb3_dacerf.envs.driving.intersection import FirstComeRoad


class StockFirstComeRoad(RegulatedRoad):
    """The intersection's first-come right of way on highway-env's own ``RegulatedRoad``."""

    respect_priorities = staticmethod(FirstComeRoad.respect_priorities)


def stock_road(road, road_class=simulation.FastRoad):
    """In place of ``simulation.fast_road``: the road highway-env built (``Road``, ``RegulatedRoad``), or the first-come one."""
    if road_class is FirstComeRoad:
        return StockFirstComeRoad(road.network, np_random=road.np_random, record_history=road.record_history)
    return road


def run(env_id: str, steps: int, highway_env_classes: bool) -> tuple[float, list]:
    """:return: steps per second, and the episodes' observations, rewards and flags"""
    patch = mock.patch.multiple(simulation, fast_road=stock_road, fast_vehicle_class=lambda vehicle_class: vehicle_class)
    with patch if highway_env_classes else contextlib.nullcontext():
        env = gym.make(env_id, density="normal")
        actions = np.random.default_rng(0).uniform(env.action_space.low, env.action_space.high, (steps, 2)).astype(np.float32)
        seed = 0
        trace = [env.reset(seed=seed)[0].tobytes()]
        start = time.perf_counter()
        for action in actions:
            obs, reward, terminated, truncated, _ = env.step(action)
            trace.append((obs.tobytes(), reward, terminated, truncated))
            if terminated or truncated:
                seed += 1
                trace.append(env.reset(seed=seed)[0].tobytes())
        return steps / (time.perf_counter() - start), trace


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=2, help="best of this many runs (the machine may be shared)")
    args = parser.parse_args()
    print(f"highway-env {highway_env.__version__}, Python {platform.python_version()}, {platform.machine()}")
    print(
        "| scenario | steps/s, highway-env's classes | steps/s, sb3_dacerf's | speed-up | same episodes |\n|---|---|---|---|---|"
    )
    identical = True
    for env_id in ("DACERF-Intersection-v0", "DACERF-Multilane-v0"):
        rates, traces = {True: 0.0, False: 0.0}, {}
        for _ in range(args.repeats):
            for stock in (True, False):
                rate, traces[stock] = run(env_id, args.steps, stock)
                rates[stock] = max(rates[stock], rate)
        same = traces[True] == traces[False]
        identical &= same
        print(f"| `{env_id}` | {rates[True]:,.0f} | {rates[False]:,.0f} | {rates[False] / rates[True]:.1f}× | {same} |")
    sys.exit(0 if identical else "the two simulations gave different episodes")
