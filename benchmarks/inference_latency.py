"""
Inference latency: one action for one observation, DACERF beside DACER (20-step diffusion), SAC and TQC.

For each space size and algorithm (untrained, ``net_arch=[256, 256]`` for all, each algorithm's other defaults:
DACER's Mish activation, the others' ReLU), four timings of a single observation:

- ``predict``: SB3's ``model.predict(obs)`` (numpy in, numpy out, preprocessing and unscaling included),
  deterministic (deployment) and stochastic (acting during training);
- ``forward``: the actor module alone on a ready tensor under ``no_grad``, ``model.actor(obs, deterministic)``.

All the (algorithm, timing) pairs of a size are called in turn, in a new random order each round, so that machine
load hits them alike; the table gives medians over the rounds and ratios to SAC. The models are built on an
environment that only has spaces (no simulator): latency does not depend on the weights or the dynamics.
Sizes: Pendulum (3 observations / 1 action), humanoid as the DACER-F paper states it (67/24; DeepMind Control's
humanoid really has 67/21) and dog (223/38).

Usage::

    python benchmarks/inference_latency.py [--quick] [--device cpu|cuda] [--threads 1] [--rounds 4000]
"""

import argparse
import platform
import random
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch as th
from gymnasium import spaces
from sb3_contrib import TQC
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_dacerf import DACER, DACERF

SIZES = {"Pendulum 3/1": (3, 1), "humanoid 67/24": (67, 24), "dog 223/38": (223, 38)}
ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"DACERF": DACERF, "DACER": DACER, "SAC": SAC, "TQC": TQC}
TIMINGS = ("predict det.", "predict stoch.", "forward det.", "forward stoch.")


class SpacesOnly(gym.Env):
    """An environment with a Box observation and action space of the given sizes, and random transitions."""

    def __init__(self, obs_dim: int, action_dim: int):
        self.observation_space = spaces.Box(-10.0, 10.0, (obs_dim,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (action_dim,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        return self.observation_space.sample(), 0.0, False, False, {}


def make_model(algorithm: type[BaseAlgorithm], obs_dim: int, action_dim: int, device: str, **kwargs) -> BaseAlgorithm:
    """An untrained model with 256x256 networks on a spaces-only environment."""
    env = SpacesOnly(obs_dim, action_dim)
    return algorithm("MlpPolicy", env, policy_kwargs=dict(net_arch=[256, 256]), device=device, seed=0, **kwargs)


def machine_name() -> str:
    """CPU model (and GPU when one is used), for the tables."""
    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        names = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines() if line.startswith("model name")]
        cpu = f"{names[0]} ({len(names)} logical cores)" if names else cpu
    gpu = f", {th.cuda.get_device_name()}" if th.cuda.is_available() else ""
    return f"{cpu}{gpu}, torch {th.__version__}"


def interleaved_medians(calls: dict[str, Callable[[], object]], rounds: int, synchronize: bool) -> dict[str, float]:
    """Median seconds per call of each function, called in a new random order every round."""
    samples: dict[str, list[float]] = {name: [] for name in calls}
    names = list(calls)
    for _ in range(rounds):
        random.shuffle(names)
        for name in names:
            start = time.perf_counter()
            calls[name]()
            if synchronize:
                th.cuda.synchronize()
            samples[name].append(time.perf_counter() - start)
    return {name: statistics.median(values) for name, values in samples.items()}


def measure(obs_dim: int, action_dim: int, device: str, rounds: int) -> dict[tuple[str, str], float]:
    """Median latency in seconds of every (algorithm, timing) pair for one space size."""
    calls = {}
    for name, algorithm in ALGORITHMS.items():
        model = make_model(algorithm, obs_dim, action_dim, device, buffer_size=1)
        model.policy.set_training_mode(False)
        observation = model.observation_space.sample()
        tensor = th.as_tensor(observation[None], device=model.device)

        def forward(actor=model.actor, tensor=tensor, deterministic=True):
            with th.no_grad():
                return actor(tensor, deterministic=deterministic)

        calls[(name, "predict det.")] = lambda m=model, o=observation: m.predict(o, deterministic=True)
        calls[(name, "predict stoch.")] = lambda m=model, o=observation: m.predict(o, deterministic=False)
        calls[(name, "forward det.")] = forward
        calls[(name, "forward stoch.")] = lambda f=forward: f(deterministic=False)
    interleaved_medians(calls, max(rounds // 10, 20), synchronize=device == "cuda")  # warm-up
    return interleaved_medians(calls, rounds, synchronize=device == "cuda")


def markdown_table(results: dict[str, dict[tuple[str, str], float]]) -> str:
    lines = [
        "| size | algorithm | " + " | ".join(f"{timing} (µs)" for timing in TIMINGS) + " | "
        + " | ".join(f"{timing} / SAC" for timing in TIMINGS) + " |",
        "|" + "---|" * (2 + 2 * len(TIMINGS)),
    ]  # fmt: skip
    for size, medians in results.items():
        for name in ALGORITHMS:
            times = [medians[(name, timing)] for timing in TIMINGS]
            ratios = [medians[(name, timing)] / medians[("SAC", timing)] for timing in TIMINGS]
            lines.append(
                f"| {size} | {name} | " + " | ".join(f"{1e6 * t:.0f}" for t in times) + " | "
                + " | ".join(f"{r:.2f}" for r in ratios) + " |"
            )  # fmt: skip
    return "\n".join(lines)


def verdict(met: bool) -> str:
    return "met" if met else "MISSED"


def targets(results: dict[str, dict[tuple[str, str], float]]) -> str:
    """The issue's targets, checked on every size and both modes."""
    lines = []
    for size, medians in results.items():
        for mode in ("det.", "stoch."):
            to_sac = medians[("DACERF", f"predict {mode}")] / medians[("SAC", f"predict {mode}")]
            predict_speedup = medians[("DACER", f"predict {mode}")] / medians[("DACERF", f"predict {mode}")]
            forward_speedup = medians[("DACER", f"forward {mode}")] / medians[("DACERF", f"forward {mode}")]
            lines.append(
                f"- {size}, {mode}: DACERF predict / SAC = {to_sac:.2f} (≤ 1.05: {verdict(to_sac <= 1.05)}); "
                f"DACER / DACERF predict = {predict_speedup:.1f}x (≥ 8: {verdict(predict_speedup >= 8)}), "
                f"forward = {forward_speedup:.1f}x (≥ 15: {verdict(forward_speedup >= 15)})"
            )
    return "\n".join(lines)


def plot(results: dict[str, dict[tuple[str, str], float]], title: str, path: Path) -> None:
    figure, axes = plt.subplots(1, len(results), figsize=(5 * len(results), 4), sharey=True)
    width = 0.8 / len(ALGORITHMS)
    for axis, (size, medians) in zip(np.atleast_1d(axes), results.items(), strict=True):
        for i, name in enumerate(ALGORITHMS):
            values = [1e3 * medians[(name, timing)] for timing in TIMINGS]
            axis.bar(np.arange(len(TIMINGS)) + (i - (len(ALGORITHMS) - 1) / 2) * width, values, width, label=name)
        axis.set_xticks(np.arange(len(TIMINGS)), TIMINGS, rotation=20)
        axis.set_yscale("log")
        axis.set_title(size)
        axis.grid(axis="y", which="both", alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("median latency, one observation (ms)")
    np.atleast_1d(axes)[0].legend()
    figure.suptitle(title, fontsize=9)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def parse_arguments(parser: argparse.ArgumentParser, plot: str) -> argparse.Namespace:
    """Add the options both speed benchmarks have (--device, --threads, --plot), parse, and apply --threads."""
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (1: steadier on a shared machine)")
    parser.add_argument(
        "--plot", type=Path, help=f"where the PNG goes (default: benchmarks/{plot}, with --quick benchmarks/results/quick/)"
    )
    args = parser.parse_args()
    if args.plot is None:  # --quick runs never overwrite the committed figures
        folder = Path(__file__).parent / "results" / "quick" if args.quick else Path(__file__).parent
        folder.mkdir(parents=True, exist_ok=True)
        args.plot = folder / plot
    th.set_num_threads(args.threads)
    random.seed(0)
    return args


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="400 rounds instead of --rounds (about a minute)")
    parser.add_argument("--rounds", type=int, default=4000, help="timed rounds per size (each calls every pair once)")
    args = parse_arguments(parser, "inference_latency.png")
    rounds = 400 if args.quick else args.rounds

    header = (
        f"{machine_name()}; device {args.device}; torch.set_num_threads({args.threads}); "
        f"{rounds} interleaved rounds{' (--quick)' if args.quick else ''}; net_arch [256, 256]"
    )
    print(header)
    results = {size: measure(obs_dim, action_dim, args.device, rounds) for size, (obs_dim, action_dim) in SIZES.items()}
    print()
    print(markdown_table(results))
    print()
    print(targets(results))
    plot(results, header, args.plot)
    print(f"\nPlot: {args.plot}")


if __name__ == "__main__":
    main()
