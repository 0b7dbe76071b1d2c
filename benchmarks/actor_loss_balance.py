"""
Balance of DACER-F's actor loss under each weighting (``flow_matching_weights``), across reward scales and shifts.

For every weighting and every reward transform (``r``, ``r + 16``, ``10 r``), DACERF trains on Pendulum-v1 for
``--timesteps`` steps; then, on ``--batches`` replay batches, the norm of the imitation term's gradient on the actor
is divided by that of the improvement term (:meth:`sb3_dacerf.DACERF.actor_gradient_ratio`). A ratio near 1 means both
terms pull the actor equally; 10 or 0.1 means one of them drowns the other. The table printed is the median ratio
per weighting and transform (one seed each).

    python benchmarks/actor_loss_balance.py                 # 1,500 steps per run, 15 runs, ~20 min on one core
    python benchmarks/actor_loss_balance.py --quick         # 300 steps per run: checks the pipeline
"""

import argparse

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import gymnasium as gym
import numpy as np
import torch as th

from sb3_dacerf import DACERF
from sb3_dacerf.dacerf.dacerf import FLOW_MATCHING_WEIGHTS

TRANSFORMS = {"r": (1.0, 0.0), "r + 16": (1.0, 16.0), "10 r": (10.0, 0.0)}


def balance(weighting: str, scale: float, shift: float, timesteps: int, batches: int, seed: int) -> float:
    env = gym.wrappers.TransformReward(gym.make("Pendulum-v1"), lambda reward: scale * reward + shift)
    model = DACERF("MlpPolicy", env, seed=seed, learning_starts=200, flow_matching_weights=weighting)
    model.learn(timesteps)
    ratios = []
    for _ in range(batches):
        replay_data = model.replay_buffer.sample(model.batch_size)
        ratios.append(model.actor_gradient_ratio(model.actor_loss_terms(replay_data)))
    return float(np.median(ratios))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--timesteps", type=int, default=1_500)
    parser.add_argument("--batches", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--weightings", nargs="+", default=list(FLOW_MATCHING_WEIGHTS), choices=FLOW_MATCHING_WEIGHTS)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    if args.quick:
        args.timesteps, args.batches = 300, 5
    th.set_num_threads(1)
    print(f"Pendulum-v1, {args.timesteps} steps, seed {args.seed}: median imitation / improvement gradient-norm ratio\n")
    print("| weighting | " + " | ".join(TRANSFORMS) + " |")
    print("|---|" + "---|" * len(TRANSFORMS))
    for weighting in args.weightings:
        cells = [
            balance(weighting, scale, shift, args.timesteps, args.batches, args.seed) for scale, shift in TRANSFORMS.values()
        ]
        print(f"| {weighting} | " + " | ".join(f"{cell:.3g}" for cell in cells) + " |", flush=True)


if __name__ == "__main__":
    main()
