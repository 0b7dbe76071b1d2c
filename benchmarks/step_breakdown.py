"""
Where a gradient step's time goes, and what ``learn()`` costs per environment step against SAC.

Two measurements, both on one torch thread (``--threads``):

- **Breakdown**: ``model.train()`` for ``--updates`` gradient steps (1,000 by default) under ``cProfile``, on a
  spaces-only environment whose replay buffer holds random transitions (as ``iteration_time.py``); the cumulative
  time of each part (replay sampling, critic update, Langevin targets, ...) per gradient step. cProfile adds a
  fixed cost to every Python call, so the parts' shares are what to read, not their absolute times.
- **learn() ratio**: DACERF and SAC with their constructor defaults, each on its own copy of a real environment
  (Pendulum-v1, DMC walker-walk), learning in alternating blocks of ``--block`` environment steps in one process
  (after a warm-up past ``learning_starts``); the median time per environment step of each and their ratio.
  Environment stepping, action selection, replay and training are all included, as users pay them.

``iteration_time.py`` imports both; run this file for them alone::

    python benchmarks/step_breakdown.py [--updates 1000] [--blocks 10] [--block 400] [--clock wall|cpu] [--skip-learn]
                                        [--skip-breakdown] [--envs ...] [--algorithms DACERF DACER SAC]
"""

from __future__ import annotations

import argparse
import cProfile
import functools
import pstats
import random

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import gymnasium as gym
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.logger import Logger
from timing import CLOCKS, interleaved_medians, machine_name

from sb3_dacerf import DACERF

# The parts of a gradient step: (label, source file ending, function name, label of the part it belongs to)
PARTS: dict[str, list[tuple[str, str, str, str | None]]] = {
    "DACERF": [
        ("replay sampling", "stable_baselines3/common/buffers.py", "sample", None),
        ("critic update", "sb3_dacerf/common/twin_critic.py", "_step", None),
        ("target update", "sb3_dacerf/common/twin_critic.py", "_update_targets", None),
        ("actor update", "sb3_dacerf/dacerf/dacerf.py", "_update_actor", None),
        ("actor loss terms", "sb3_dacerf/dacerf/dacerf.py", "actor_loss_terms", "actor update"),
        # the gradient's set-up (critic features, state part of the first layer) and the 20-step loop
        ("Langevin set-up", "sb3_dacerf/dacerf/policies.py", "__init__", "actor loss terms"),
        ("Langevin loop", "sb3_dacerf/dacerf/dacerf.py", "langevin_targets", "actor loss terms"),
        ("entropy estimate", "sb3_dacerf/dacerf/dacerf.py", "_entropy_and_spread", "actor update"),
        ("balance diagnostic", "sb3_dacerf/dacerf/dacerf.py", "_actor_gradient_ratio", "actor update"),
    ],
    "DACER": [
        ("replay sampling", "stable_baselines3/common/buffers.py", "sample", None),
        ("critic update", "sb3_dacerf/common/twin_critic.py", "_step", None),
        ("target update", "sb3_dacerf/common/twin_critic.py", "_update_targets", None),
        ("entropy estimate", "sb3_dacerf/dacer/dacer.py", "_estimate_entropy", None),
    ],
    "SAC": [("replay sampling", "stable_baselines3/common/buffers.py", "sample", None)],
}


def _cumulative(stats: pstats.Stats, path_end: str, function: str) -> float:
    """Cumulative seconds of the functions named ``function`` defined in a file ending with ``path_end``."""
    total = 0.0
    for (filename, _, name), (_, _, _, cumulative, _) in stats.stats.items():  # type: ignore[attr-defined]
        if name == function and filename.replace("\\", "/").endswith(path_end):
            total += cumulative
    return total


def breakdown(model: BaseAlgorithm, name: str, n_updates: int, batch_size: int = 256, clock: str = "wall") -> dict[str, float]:
    """
    Milliseconds per gradient step of each part of ``name``'s :data:`PARTS` over ``n_updates`` steps of
    ``model.train()`` under cProfile, what a part spends outside its listed sub-parts as ``"<part>: other"``, and the
    whole step as ``"total"``.

    :param model: A model whose replay buffer is filled (e.g. ``iteration_time.ready_to_train``)
    :param name: Its key in :data:`PARTS` (``"DACERF"``, ``"DACER"``, ``"SAC"``)
    :param n_updates: Gradient steps profiled (after 10 unprofiled ones)
    :param batch_size: Replay batch size
    :param clock: ``"wall"`` or ``"cpu"`` (this process's CPU time), the profiler's timer
    """
    model.train(gradient_steps=10, batch_size=batch_size)
    profiler = cProfile.Profile(CLOCKS[clock])
    profiler.enable()
    model.train(gradient_steps=n_updates, batch_size=batch_size)
    profiler.disable()
    stats = pstats.Stats(profiler)
    train_files = {
        "DACERF": "sb3_dacerf/dacerf/dacerf.py",
        "DACER": "sb3_dacerf/dacer/dacer.py",
        "SAC": "stable_baselines3/sac/sac.py",
    }
    per_step = 1e3 / n_updates
    result = {"total": per_step * _cumulative(stats, train_files[name], "train")}
    children: dict[str, float] = {}
    for label, path_end, function, parent in PARTS[name]:
        result[label] = per_step * _cumulative(stats, path_end, function)
        if parent is not None:
            children[parent] = children.get(parent, 0.0) + result[label]
    for parent, value in children.items():
        result[f"{parent}: other"] = result[parent] - value
    top = sum(result[label] for label, _, _, parent in PARTS[name] if parent is None)
    # DACER's and SAC's actor updates are written inside train(): they are in this remainder
    result["rest of train()"] = result["total"] - top
    return result


def print_breakdown(results: dict[str, dict[str, float]]) -> None:
    """A markdown table: one row per part, one column per algorithm (ms per gradient step and share of the step)."""
    labels = list(dict.fromkeys(label for parts in results.values() for label in parts))
    labels = [label for label in labels if label != "total"] + ["total"]
    print("| part | " + " | ".join(f"{name} (ms, share)" for name in results) + " |")
    print("|---|" + "---|" * len(results))
    for label in labels:
        cells = []
        for parts in results.values():
            cells.append(f"{parts[label]:.2f} ({100 * parts[label] / parts['total']:.0f}%)" if label in parts else "")
        print(f"| {label} | " + " | ".join(cells) + " |")


def make_learner(algorithm: type[BaseAlgorithm], env_id: str, seed: int = 0) -> BaseAlgorithm:
    """A model with its algorithm's defaults on ``env_id``, logging nowhere."""
    model = algorithm("MlpPolicy", gym.make(env_id), seed=seed, device="cpu")
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


def learn_ratio(
    env_id: str, blocks: int, block: int, clock: str = "wall", algorithms: dict[str, type[BaseAlgorithm]] | None = None
) -> dict[str, float]:
    """
    Median seconds per environment step of ``learn()`` for each algorithm (DACERF and SAC by default), in
    ``blocks`` alternating blocks of ``block`` steps each (random order within each round), after a warm-up block.
    """
    algorithms = algorithms or {"DACERF": DACERF, "SAC": SAC}
    models = {name: make_learner(algorithm, env_id) for name, algorithm in algorithms.items()}
    for model in models.values():  # past learning_starts (100 for both), so that every timed step trains
        model.learn(block, reset_num_timesteps=False)
    calls = {name: functools.partial(model.learn, block, reset_num_timesteps=False) for name, model in models.items()}
    medians = interleaved_medians(calls, rounds=blocks, synchronize=False, clock=clock)
    return {str(name): seconds / block for name, seconds in medians.items()}


LEARN_ENVS = ("Pendulum-v1", "DMC-walker-walk-v0")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--updates", type=int, default=1000, help="gradient steps profiled per algorithm")
    parser.add_argument("--blocks", type=int, default=10, help="timed blocks of learn() per algorithm and environment")
    parser.add_argument("--block", type=int, default=400, help="environment steps per block")
    parser.add_argument("--envs", nargs="+", default=list(LEARN_ENVS))
    parser.add_argument("--algorithms", nargs="+", default=list(PARTS), choices=list(PARTS), help="for the breakdown")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--clock", default="wall", choices=list(CLOCKS))
    parser.add_argument("--skip-learn", action="store_true", help="the breakdown only")
    parser.add_argument("--skip-breakdown", action="store_true", help="the learn() ratios only")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    random.seed(0)
    from iteration_time import ready_to_train

    import sb3_dacerf  # noqa: F401  (registers the DMC ids)

    print(f"{machine_name()}; torch.set_num_threads({args.threads}); {args.clock} clock\n")
    if not args.skip_breakdown:
        print(f"Breakdown of a gradient step (humanoid 67/24 sizes, batch 256, {args.updates} steps under cProfile):\n")
        results = {
            name: breakdown(ready_to_train(name, 67, 24, "cpu"), name, args.updates, clock=args.clock) for name in args.algorithms
        }
        print_breakdown(results)
        print()
    if not args.skip_learn:
        print(f"learn() per environment step ({args.blocks} alternating blocks of {args.block} steps, {args.clock} clock):\n")
        print("| environment | DACERF (ms/step) | SAC (ms/step) | DACERF / SAC |")
        print("|---|---|---|---|")
        for env_id in args.envs:
            medians = learn_ratio(env_id, args.blocks, args.block, args.clock)
            print(
                f"| {env_id} | {1e3 * medians['DACERF']:.2f} | {1e3 * medians['SAC']:.2f} | "
                f"{medians['DACERF'] / medians['SAC']:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
