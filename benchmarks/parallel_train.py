"""
Wall-clock per environment step of DACERF (or DACER) with and without RL Zoo's ``ParallelTrainCallback``, side by
side in one process.

Two models of the same algorithm, with the constructor defaults (those of ``hyperparams/<algo>.yml``), collect
``--warm-up`` random steps each (``learning_starts``); then, in ``--blocks`` rounds, each model learns ``--block-steps``
more steps, in a new random order each round: one as SB3 trains it (one gradient step per environment step), the other
with ``ParallelTrainCallback(gradient_steps=--gradient-steps)`` (the gradient steps in a thread, in rounds, while the
model collects). A block ends when its last round of gradient steps has ended. The table gives, per variant, the
median over the blocks of the wall-clock time per environment step and per gradient step, the gradient steps taken per
environment step, and the ratio of the two variants' times per environment step.

    PYTHONPATH=. python benchmarks/parallel_train.py            # Pendulum-v1 and DMC-cheetah-run-v0, 3 blocks of 1000 steps
    PYTHONPATH=. python benchmarks/parallel_train.py --quick    # 2 blocks of 200 steps (benchmarks/results/quick/)
"""

from __future__ import annotations

import argparse
import random
import shlex
import statistics
import sys
import time
import warnings
from pathlib import Path

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import rl_zoo3.callbacks
import torch as th
from rl_zoo3.callbacks import ParallelTrainCallback
from timing import load_average, machine_name

from sb3_dacerf.zoo import ALGORITHMS, register

RESULTS = Path(__file__).resolve().parent / "results"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--algo", default="dacerf", choices=sorted(ALGORITHMS))
    parser.add_argument("--envs", nargs="+", default=["Pendulum-v1", "DMC-cheetah-run-v0"])
    parser.add_argument("--blocks", type=int, default=3, help="timed blocks per variant")
    parser.add_argument("--block-steps", type=int, default=1000, help="environment steps per block")
    parser.add_argument("--warm-up", type=int, default=1000, help="random steps before the first block (learning_starts)")
    parser.add_argument("--gradient-steps", type=int, default=100, help="ParallelTrainCallback's gradient_steps (its default)")
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    parser.add_argument("--quick", action="store_true", help="2 blocks of 200 steps, 200 warm-up steps")
    args = parser.parse_args()
    if args.quick:
        args.blocks, args.block_steps, args.warm_up = 2, 200, 200
    th.set_num_threads(args.threads)
    random.seed(0)
    register(rl_zoo3.callbacks)  # what the start-up hook does when RL Zoo is imported

    algorithm = ALGORITHMS[args.algo]
    load_before = load_average()
    rows = []
    for env_id in args.envs:
        models = {
            variant: algorithm("MlpPolicy", env_id, learning_starts=args.warm_up, seed=0) for variant in ("SB3", "parallel")
        }
        for model in models.values():
            with warnings.catch_warnings():  # random actions only: learn() warns that it took no gradient step
                warnings.simplefilter("ignore", UserWarning)
                model.learn(args.warm_up)
        per_step: dict[str, list[float]] = {variant: [] for variant in models}
        per_update: dict[str, list[float]] = {variant: [] for variant in models}
        steps, updates = dict.fromkeys(models, 0), dict.fromkeys(models, 0)
        for _ in range(args.blocks):
            order = list(models)
            random.shuffle(order)
            for variant in order:
                model = models[variant]
                callback = ParallelTrainCallback(gradient_steps=args.gradient_steps) if variant == "parallel" else None
                start, timesteps, n_updates = time.perf_counter(), model.num_timesteps, model._n_updates
                model.learn(args.block_steps, callback=callback, reset_num_timesteps=False)
                seconds = time.perf_counter() - start
                steps[variant] += model.num_timesteps - timesteps
                updates[variant] += model._n_updates - n_updates
                per_step[variant].append(seconds / (model.num_timesteps - timesteps))
                per_update[variant].append(seconds / max(model._n_updates - n_updates, 1))
        medians = {variant: statistics.median(values) for variant, values in per_step.items()}
        for variant in models:
            rows.append(
                f"| {env_id} | {variant} | {1000 * medians[variant]:.1f} | {updates[variant] / steps[variant]:.2f} "
                f"| {1000 * statistics.median(per_update[variant]):.1f} | {medians[variant] / medians['SB3']:.2f} |"
            )
    command = "PYTHONPATH=. python benchmarks/parallel_train.py " + shlex.join(sys.argv[1:])
    lines = [
        f"`{command.strip()}`",
        "",
        f"`{machine_name()}; torch.set_num_threads({args.threads}); {load_before} at the start, {load_average()} at the "
        f"end; {args.algo}, {args.blocks} blocks of {args.block_steps} steps per variant after {args.warm_up} random "
        f"steps; ParallelTrainCallback(gradient_steps={args.gradient_steps})`",
        "",
        "| environment | training | ms per environment step (median of blocks) | gradient steps per environment step "
        "| ms per gradient step (median of blocks) | time per environment step / SB3's |",
        "|---|---|---|---|---|---|",
        *rows,
    ]
    table = "\n".join(lines)
    print(table)
    folder = RESULTS / "quick" if args.quick else RESULTS
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"parallel_train_{args.algo}.md").write_text(table + "\n")


if __name__ == "__main__":
    main()
