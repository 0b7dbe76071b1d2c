"""
Training iteration time: one gradient step of DACERF beside DACER (20-step diffusion), SAC and TQC.

A gradient step is what ``model.train()`` does per update, environment excluded: replay sampling, the critic update
and the actor update amortised over the policy delay. Every configuration runs its algorithm's own defaults apart
from ``net_arch=[256, 256]`` (see ``timing.CONFIGURATIONS``): DACERF with the paper's 20 Langevin steps, policy
delay 3 and one sampling step (no shortcut), ReLU; DACER with 20 diffusion steps, policy delay 2 and Mish
activations, as in its official code; "DACER (ReLU)" the same with ReLU, for DACER against DACERF at equal
activation; SAC and TQC updating their actor every step. ``model.train(gradient_steps=6)`` is timed (6 covers both
policy delays) and divided by 6; the configurations of one (size, batch) are called in turn, in one process, in a
new random order each round, and the tables give medians, ratios to SAC and DACER / DACERF in both comparisons.
DACER's entropy estimate (a Gaussian mixture fitted to 200 actions per state of a batch, once every 10,000
updates) is timed apart and given amortised. Spaces: ``timing.SIZES``; the replay buffer holds random transitions.

Usage::

    python benchmarks/iteration_time.py [--quick] [--device cpu|cuda] [--threads 1] [--clock wall|cpu] [--rounds 40]
                                        [--sizes ...] [--batch-sizes 256 512]
"""

import argparse
import textwrap
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.logger import Logger
from timing import (
    CLOCKS,
    CONFIGURATIONS,
    NET_ARCH,
    SIZES,
    add_common_arguments,
    apply_common_arguments,
    interleaved_medians,
    load_average,
    machine_name,
    make_model,
    verdict,
)

from sb3_dacerf import DACER

GRADIENT_STEPS = 6  # a multiple of DACERF's policy delay (3) and DACER's (2)
BUFFER_SIZE = 10_000
# DACER against DACERF: (label, DACER configuration)
COMPARISONS = {"own activations (DACER Mish, DACERF ReLU)": "DACER", "equal activation (both ReLU)": "DACER (ReLU)"}
# DACER-F paper, "Time Efficiency": 70.1 ms (DACER), 20.8 ms (DACER-F), 11.7 ms (DSAC) per training step
PAPER = {"DACER / DACERF": 70.1 / 20.8, "DACERF / DSAC": 20.8 / 11.7, "DACER / DSAC": 70.1 / 11.7}


def ready_to_train(name: str, obs_dim: int, action_dim: int, device: str, **kwargs: Any) -> BaseAlgorithm:
    """A model of one configuration whose replay buffer is full of random transitions, logging nowhere."""
    model = make_model(name, obs_dim, action_dim, device, buffer_size=BUFFER_SIZE, **kwargs)
    buffer = model.replay_buffer
    rng = np.random.default_rng(0)
    buffer.observations[:] = rng.normal(size=buffer.observations.shape)
    buffer.next_observations[:] = rng.normal(size=buffer.next_observations.shape)
    buffer.actions[:] = rng.uniform(-1, 1, size=buffer.actions.shape)
    buffer.rewards[:] = rng.normal(size=buffer.rewards.shape)
    buffer.full = True
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


def measure(
    obs_dim: int, action_dim: int, batch_size: int, device: str, rounds: int, names: list[str], clock: str = "wall"
) -> dict[str, float]:
    """Median seconds per gradient step of each configuration, and DACER's entropy estimate (seconds per call)."""
    models = {name: ready_to_train(name, obs_dim, action_dim, device) for name in names}
    calls = {
        name: (lambda m=model: m.train(gradient_steps=GRADIENT_STEPS, batch_size=batch_size)) for name, model in models.items()
    }
    # Warm-up; it also runs DACER's first entropy estimate (update 1), so that the timed rounds hold none
    interleaved_medians(calls, 2, synchronize=device == "cuda")
    medians = {
        name: value / GRADIENT_STEPS for name, value in interleaved_medians(calls, rounds, device == "cuda", clock).items()
    }
    dacer = models["DACER"]
    assert isinstance(dacer, DACER)
    observations = dacer.replay_buffer.sample(batch_size).observations
    start = CLOCKS[clock]()
    dacer._estimate_entropy(observations)
    medians["DACER entropy estimate"] = CLOCKS[clock]() - start
    return medians


def plot(
    results: dict[tuple[str, int], dict[str, float]],
    names: list[str],
    sizes: list[str],
    batch_sizes: list[int],
    title: str,
    path: Path,
) -> None:
    """Bars of the median time per gradient step, one panel per batch size."""
    figure, axes = plt.subplots(1, len(batch_sizes), figsize=(max(7, 6 * len(batch_sizes)), 4.4), squeeze=False)
    width = 0.8 / len(names)
    for axis, batch_size in zip(axes[0], batch_sizes, strict=True):
        for i, name in enumerate(names):
            values = [1e3 * results[(size, batch_size)][name] for size in sizes]
            axis.bar(np.arange(len(sizes)) + (i - (len(names) - 1) / 2) * width, values, width, label=name)
        axis.set_xticks(np.arange(len(sizes)), sizes)
        axis.set_title(f"batch {batch_size}")
        axis.set_ylabel("median time per gradient step (ms)")
        axis.grid(axis="y", alpha=0.3)
        axis.set_ylim(top=1.3 * axis.get_ylim()[1])  # room for the legend above the tallest bars
    axes[0][0].legend(ncol=3, fontsize="small", loc="upper left")
    figure.suptitle("\n".join(textwrap.wrap(title, 110)), fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="5 rounds, batch 256 only (about 2 minutes)")
    parser.add_argument("--rounds", type=int, default=40, help="timed rounds per (size, batch)")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--sizes", nargs="+", choices=list(SIZES), default=list(SIZES), metavar="SIZE", help=f"of {list(SIZES)}")
    add_common_arguments(parser, plot="iteration_time.png")
    args = parser.parse_args()
    apply_common_arguments(parser, args, plot="iteration_time.png")
    rounds, batch_sizes = (5, [256]) if args.quick else (args.rounds, args.batch_sizes)
    names = list(CONFIGURATIONS)
    dacerfs = [name for name in names if name.startswith("DACERF")]

    header = (
        f"{machine_name()}; device {args.device}; torch.set_num_threads({args.threads}); {args.clock} clock; "
        f"{rounds} interleaved rounds of train(gradient_steps={GRADIENT_STEPS}){' (--quick)' if args.quick else ''}; "
        f"net_arch {NET_ARCH}; {load_average()} at start"
    )
    print(header, flush=True)
    grid(args, names, dacerfs, rounds, batch_sizes, header)


def grid(
    args: argparse.Namespace, names: list[str], dacerfs: list[str], rounds: int, batch_sizes: list[int], header: str
) -> None:
    """The time per gradient step of every configuration, size and batch size: tables, verdicts and the plot."""
    results = {
        (size, batch_size): measure(*SIZES[size], batch_size, args.device, rounds, names, args.clock)
        for size in args.sizes
        for batch_size in batch_sizes
    }
    print(f"{load_average()} at the end\n")

    columns = [f"{name} (ms)" for name in names] + [f"{name} / SAC" for name in names] + ["DACER entropy estimate (s; ms/step)"]
    print("| size | batch | " + " | ".join(columns) + " |")
    print("|" + "---|" * (len(columns) + 2))
    for (size, batch_size), medians in results.items():
        estimate = medians["DACER entropy estimate"]
        print(
            f"| {size} | {batch_size} | " + " | ".join(f"{1e3 * medians[name]:.1f}" for name in names) + " | "
            + " | ".join(f"{medians[name] / medians['SAC']:.2f}" for name in names) + " | "
            + f"{estimate:.2f}; {1e3 * estimate / 10_000:.2f} |"
        )  # fmt: skip

    print()
    pairs = [(label, dacer, dacerf) for label, dacer in COMPARISONS.items() for dacerf in dacerfs]
    print("| size | batch | " + " | ".join(f"{dacer} / {dacerf}" for _, dacer, dacerf in pairs) + " |")
    print("|" + "---|" * (len(pairs) + 2))
    for (size, batch_size), medians in results.items():
        print(f"| {size} | {batch_size} | " + " | ".join(f"{medians[d] / medians[f]:.2f}" for _, d, f in pairs) + " |")
    print(
        "\n" + ", ".join(f"{label}: {dacer} / DACERF" for label, dacer in COMPARISONS.items())
        + ". The DACER-F paper (its implementations; i9-12900K CPU, RTX 3090 Ti GPU): "
        + ", ".join(f"{key} = {value:.2f}" for key, value in PAPER.items())
    )  # fmt: skip
    print()
    for (size, batch_size), medians in results.items():
        for name in dacerfs:
            to_sac = medians[name] / medians["SAC"]
            line = f"- {size}, batch {batch_size}: {name} / SAC = {to_sac:.2f} (≤ 2.6 on CPU: {verdict(to_sac <= 2.6)})"
            for dacer in COMPARISONS.values():
                speedup = medians[dacer] / medians[name]
                line += f"; {dacer} / {name} = {speedup:.2f} (≥ 3.4: {verdict(speedup >= 3.4)})"
            print(line)

    plot(results, names, args.sizes, batch_sizes, header, args.plot)
    print(f"\nPlot: {args.plot}")


if __name__ == "__main__":
    main()
