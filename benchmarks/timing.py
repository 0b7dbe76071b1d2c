"""
The timing harness shared by the speed benchmarks (``iteration_time.py``, ``latency.py``).

- :class:`SpacesOnly`: an environment that only has spaces, so that models can be built without a simulator;
- :data:`SIZES`: the space sizes of the DACER-F paper's figures;
- :data:`CONFIGURATIONS` and :func:`make_model`: the algorithms compared, each with its own defaults, plus DACER
  with ReLU so that DACER and DACERF can also be compared at equal activation;
- :func:`interleaved_medians`: every timed call in turn, in a new random order each round, medians over rounds;
- :func:`add_common_arguments` / :func:`apply_common_arguments`: ``--device``, ``--threads``, ``--clock``, ``--plot``;
- :func:`machine_name` and :func:`load_average`: what the tables say about where they were measured.

Not an entry point: run the scripts that import it.
"""

from __future__ import annotations

import argparse
import os
import platform
import random
import statistics
import time
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Any

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from sb3_contrib import TQC
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from torch import nn

from sb3_dacerf import DACER, DACERF

BENCHMARKS = Path(__file__).resolve().parent
SIZES = {"Pendulum 3/1": (3, 1), "humanoid 67/24": (67, 24), "dog 223/38": (223, 38)}
NET_ARCH = [256, 256]

# name: (algorithm, extra policy_kwargs). Every model gets net_arch NET_ARCH; the rest are the algorithm's defaults:
# DACER's Mish (as in its official code), ReLU for the others (SB3's default, which DACERF keeps).
# "DACER (ReLU)" differs from "DACER" only by its activation: DACER against DACERF at equal activation.
# "DACERF (MLP critics)" differs from "DACERF" only by its critics (SB3's MLP instead of LayerNorm, the earlier default),
# "DACERF (CrossQ critics)" by its critics too (batch renormalisation, no target networks, one joint forward pass).
CONFIGURATIONS: dict[str, tuple[type[BaseAlgorithm], dict[str, Any]]] = {
    "DACERF": (DACERF, {}),
    "DACERF (MLP critics)": (DACERF, dict(critic="mlp")),
    "DACERF (CrossQ critics)": (DACERF, dict(critic="batch_renorm")),
    "DACER": (DACER, {}),
    "DACER (ReLU)": (DACER, dict(activation_fn=nn.ReLU)),
    "SAC": (SAC, {}),
    "TQC": (TQC, {}),
}


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


def make_model(name: str, obs_dim: int, action_dim: int, device: str, **kwargs: Any) -> BaseAlgorithm:
    """
    An untrained model of one configuration on a spaces-only environment.

    :param name: a key of :data:`CONFIGURATIONS`
    :param kwargs: constructor arguments (``buffer_size``, ...)
    """
    algorithm, policy_kwargs = CONFIGURATIONS[name]
    env = SpacesOnly(obs_dim, action_dim)
    return algorithm("MlpPolicy", env, policy_kwargs=dict(net_arch=NET_ARCH, **policy_kwargs), device=device, seed=0, **kwargs)


def machine_name() -> str:
    """CPU model (and GPU when one is used) and torch version, for the tables."""
    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        names = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines() if line.startswith("model name")]
        cpu = f"{names[0]} ({len(names)} logical cores)" if names else cpu
    gpu = f", {th.cuda.get_device_name()}" if th.cuda.is_available() else ""
    return f"{cpu}{gpu}, torch {th.__version__}"


def load_average() -> str:
    """The 1-minute load average and the number of CPUs: absolute times on a loaded machine are slower, ratios less so."""
    if not hasattr(os, "getloadavg"):
        return "load average unknown"
    return f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"


CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def interleaved_medians(
    calls: dict[Hashable, Callable[[], object]], rounds: int, synchronize: bool, clock: str = "wall"
) -> dict[Hashable, float]:
    """
    Median seconds per call of each function, every function called once per round in a new random order, so that
    changes of machine load hit them alike.

    :param synchronize: wait for CUDA after each call (GPU timings)
    :param clock: ``"wall"`` (``time.perf_counter``) or ``"cpu"`` (``time.process_time``, the CPU time of this
        process: the time other processes hold the core is not counted, their effect on caches still is)
    """
    now = CLOCKS[clock]
    samples: dict[Hashable, list[float]] = {name: [] for name in calls}
    names = list(calls)
    for _ in range(rounds):
        random.shuffle(names)
        for name in names:
            start = now()
            calls[name]()
            if synchronize:
                th.cuda.synchronize()
            samples[name].append(now() - start)
    return {name: statistics.median(values) for name, values in samples.items()}


def verdict(met: bool) -> str:
    return "met" if met else "MISSED"


def add_common_arguments(parser: argparse.ArgumentParser, plot: str | None = None) -> None:
    """``--device``, ``--threads`` and ``--clock``; ``--plot`` when the script draws ``plot`` (a PNG name)."""
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (1: steadier on a shared machine)")
    parser.add_argument(
        "--clock",
        default="wall",
        choices=list(CLOCKS),
        help="wall: time.perf_counter; cpu: this process's CPU time (time.process_time), which leaves out the time "
        "other processes hold the core: for a machine busy with other work (CPU only, and with --threads 1)",
    )
    if plot is not None:
        parser.add_argument(
            "--plot", type=Path, help=f"where the PNG goes (default: benchmarks/{plot}, with --quick benchmarks/results/quick/)"
        )


def apply_common_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace, plot: str | None = None) -> None:
    """Check ``--device``, set the torch threads and the shuffling seed, and resolve the default ``--plot``."""
    if args.device == "cuda" and not th.cuda.is_available():
        parser.error("--device cuda: no CUDA device visible to PyTorch (use --device cpu)")
    if args.device == "cuda" and args.clock == "cpu":
        parser.error("--clock cpu does not count the GPU's work: use --clock wall with --device cuda")
    if args.clock == "cpu" and args.threads != 1:
        parser.error("--clock cpu adds up the CPU time of all threads: use it with --threads 1")
    if plot is not None and args.plot is None:  # --quick runs never overwrite the committed figures
        folder = BENCHMARKS / "results" / "quick" if getattr(args, "quick", False) else BENCHMARKS
        folder.mkdir(parents=True, exist_ok=True)
        args.plot = folder / plot
    th.set_num_threads(args.threads)
    random.seed(0)
