"""
Environment steps per second of the ``DMC-*`` ids with random actions (no agent), single process.

    python benchmarks/dmc_env_speed.py [--steps 20000] [--env-ids DMC-humanoid-stand-v0 DMC-dog-run-v0]

(with sb3_dacerf installed, or ``PYTHONPATH=.`` from the repository root)
"""

import argparse
import platform
import time

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import gymnasium as gym
import mujoco
import numpy as np

import sb3_dacerf  # noqa: F401  (registers the ids)


def steps_per_second(env_id: str, n_steps: int, seed: int = 0) -> float:
    """
    :param env_id: registered id
    :param n_steps: steps to time (resets included, actions drawn beforehand)
    :param seed: seed of the first reset and of the actions
    :return: steps per second
    """
    env = gym.make(env_id)
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, size=(n_steps, *env.action_space.shape)).astype(np.float32)
    env.reset(seed=seed)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return n_steps / elapsed


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-ids", nargs="+", default=["DMC-humanoid-stand-v0", "DMC-dog-run-v0"])
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=3, help="best of this many runs (the machine may be shared)")
    args = parser.parse_args()

    python = f"{platform.python_implementation()} {platform.python_version()}"
    print(f"mujoco {mujoco.__version__}, {python}, {platform.processor() or platform.machine()}")
    for env_id in args.env_ids:
        runs = [steps_per_second(env_id, args.steps, seed) for seed in range(args.repeats)]
        print(f"{env_id:<28} {max(runs):>8,.0f} steps/s (best of {args.repeats}; all: {', '.join(f'{r:,.0f}' for r in runs)})")
