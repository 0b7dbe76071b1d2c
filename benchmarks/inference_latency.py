"""
Inference latency: one action for one observation, DACERF beside DACER (20-step diffusion), SAC and TQC.

For each space size and configuration (untrained, ``net_arch=[256, 256]`` for all; see ``timing.CONFIGURATIONS``:
every algorithm with its own defaults, DACER's Mish activation and the others' ReLU, plus "DACER (ReLU)", DACER
with ReLU, for the comparison at equal activation), four timings of a single observation:

- ``predict``: SB3's ``model.predict(obs)`` (numpy in, numpy out, preprocessing and unscaling included),
  deterministic (deployment) and stochastic (acting during training);
- ``forward``: the actor module alone on a ready tensor under ``no_grad``, ``model.actor(obs, deterministic)``.

All the (configuration, timing) pairs of a size are called in turn, in a new random order each round, in one
process, so that machine load hits them alike; the tables give medians over the rounds, ratios to SAC, and
DACER / DACERF both with each algorithm's own activation and at equal activation. The models are built on an
environment that only has spaces (no simulator): latency does not depend on the weights or the dynamics.
Sizes: Pendulum (3 observations / 1 action), humanoid as the DACER-F paper states it (67/24; DeepMind Control's
humanoid really has 67/21) and dog (223/38).

Usage::

    python benchmarks/inference_latency.py [--quick] [--device cpu|cuda] [--threads 1] [--clock wall|cpu] [--rounds 4000]
                                           [--sizes ...]
"""

import argparse
import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch as th
from timing import (
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

TIMINGS = ("predict det.", "predict stoch.", "forward det.", "forward stoch.")
# DACER against DACERF: (label, DACER configuration)
COMPARISONS = {
    "each algorithm's defaults (DACER Mish, DACERF ReLU)": "DACER",
    "equal activation (both ReLU)": "DACER (ReLU)",
}
PAPER_RATIO = 6.25  # DACER-F paper, "Time Efficiency": inference 1.75 ms (DACER) against 0.28 ms (DACER-F)


def measure(obs_dim: int, action_dim: int, device: str, rounds: int, clock: str = "wall") -> dict[tuple[str, str], float]:
    """Median latency in seconds of every (configuration, timing) pair for one space size."""
    calls = {}
    for name in CONFIGURATIONS:
        model = make_model(name, obs_dim, action_dim, device, buffer_size=1)
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
    return interleaved_medians(calls, rounds, synchronize=device == "cuda", clock=clock)


def markdown_table(results: dict[str, dict[tuple[str, str], float]]) -> str:
    lines = [
        "| size | configuration | " + " | ".join(f"{timing} (µs)" for timing in TIMINGS) + " | "
        + " | ".join(f"{timing} / SAC" for timing in TIMINGS) + " |",
        "|" + "---|" * (2 + 2 * len(TIMINGS)),
    ]  # fmt: skip
    for size, medians in results.items():
        for name in CONFIGURATIONS:
            times = [medians[(name, timing)] for timing in TIMINGS]
            ratios = [medians[(name, timing)] / medians[("SAC", timing)] for timing in TIMINGS]
            lines.append(
                f"| {size} | {name} | " + " | ".join(f"{1e6 * t:.0f}" for t in times) + " | "
                + " | ".join(f"{r:.2f}" for r in ratios) + " |"
            )  # fmt: skip
    return "\n".join(lines)


def ratio_table(results: dict[str, dict[tuple[str, str], float]]) -> str:
    """DACER / DACERF in both configurations, beside the paper's ratio."""
    lines = [
        "| size | DACER / DACERF, compared at | " + " | ".join(TIMINGS) + " |",
        "|" + "---|" * (2 + len(TIMINGS)),
    ]
    for size, medians in results.items():
        for label, dacer in COMPARISONS.items():
            ratios = [medians[(dacer, timing)] / medians[("DACERF", timing)] for timing in TIMINGS]
            lines.append(f"| {size} | {label} | " + " | ".join(f"{r:.1f}x" for r in ratios) + " |")
    lines.append(f"\nThe DACER-F paper's ratio (its implementations; i9-12900K CPU, RTX 3090 Ti GPU): {PAPER_RATIO}x.")
    return "\n".join(lines)


def targets(results: dict[str, dict[tuple[str, str], float]]) -> str:
    """The speed targets, checked on every size, both modes and both comparisons."""
    lines = []
    for size, medians in results.items():
        for mode in ("det.", "stoch."):
            to_sac = medians[("DACERF", f"predict {mode}")] / medians[("SAC", f"predict {mode}")]
            line = f"- {size}, {mode}: DACERF predict / SAC = {to_sac:.2f} (≤ 1.05: {verdict(to_sac <= 1.05)})"
            for dacer in COMPARISONS.values():
                predict_speedup = medians[(dacer, f"predict {mode}")] / medians[("DACERF", f"predict {mode}")]
                forward_speedup = medians[(dacer, f"forward {mode}")] / medians[("DACERF", f"forward {mode}")]
                line += (
                    f"; {dacer} / DACERF predict = {predict_speedup:.1f}x (≥ 8: {verdict(predict_speedup >= 8)}), "
                    f"forward = {forward_speedup:.1f}x (≥ 15: {verdict(forward_speedup >= 15)})"
                )
            lines.append(line)
    return "\n".join(lines)


def plot(results: dict[str, dict[tuple[str, str], float]], title: str, path: Path) -> None:
    figure, axes = plt.subplots(1, len(results), figsize=(5 * len(results), 4), sharey=True, squeeze=False)
    names = list(CONFIGURATIONS)
    width = 0.8 / len(names)
    for axis, (size, medians) in zip(axes[0], results.items(), strict=True):
        for i, name in enumerate(names):
            values = [1e3 * medians[(name, timing)] for timing in TIMINGS]
            axis.bar(np.arange(len(TIMINGS)) + (i - (len(names) - 1) / 2) * width, values, width, label=name)
        axis.set_xticks(np.arange(len(TIMINGS)), TIMINGS, rotation=20)
        axis.set_yscale("log")
        axis.set_title(size)
        axis.grid(axis="y", which="both", alpha=0.3)
    axes[0][0].set_ylabel("median latency, one observation (ms)")
    figure.legend(*axes[0][0].get_legend_handles_labels(), loc="lower center", ncol=len(names), fontsize="small")
    figure.suptitle("\n".join(textwrap.wrap(title, 200)), fontsize=8)
    figure.tight_layout(rect=(0, 0.06, 1, 1))
    figure.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="400 rounds instead of --rounds (about a minute)")
    parser.add_argument("--rounds", type=int, default=4000, help="timed rounds per size (each calls every pair once)")
    parser.add_argument("--sizes", nargs="+", choices=list(SIZES), default=list(SIZES), metavar="SIZE", help=f"of {list(SIZES)}")
    add_common_arguments(parser, plot="inference_latency.png")
    args = parser.parse_args()
    apply_common_arguments(parser, args, plot="inference_latency.png")
    rounds = 400 if args.quick else args.rounds

    header = (
        f"{machine_name()}; device {args.device}; torch.set_num_threads({args.threads}); {args.clock} clock; "
        f"{rounds} interleaved rounds{' (--quick)' if args.quick else ''}; net_arch {NET_ARCH}; {load_average()} at start"
    )
    print(header, flush=True)
    results = {size: measure(*SIZES[size], args.device, rounds, args.clock) for size in args.sizes}
    print(f"{load_average()} at the end\n")
    print(markdown_table(results))
    print()
    print(ratio_table(results))
    print()
    print(targets(results))
    plot(results, header, args.plot)
    print(f"\nPlot: {args.plot}")


if __name__ == "__main__":
    main()
