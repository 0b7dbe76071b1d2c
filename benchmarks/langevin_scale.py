"""
How far DACERF's Langevin steps move the replay actions, on the critics of saved runs: the reward-scale check behind
``langevin_normalize_gradient``.

For each checkpoint of ``benchmarks/learning_curves.py`` (the folder ``<out>/checkpoints/<env>/<variant>-seed<N>``)
it draws a replay batch and prints the scale of the critic (mean ``|Q|``), the action gradient ``|∇_a Q|`` per
coordinate (median and 90th percentile, in the policy's [-1, 1] action units), the move of the first Langevin step,
and, for the paper's update and for the normalised one, the median distance ``|a* - a_B|``, the share of target
coordinates at an action bound and the mean Q gain ``Q(s, a*) - Q(s, a_B)``::

    python benchmarks/langevin_scale.py benchmarks/results/checkpoints/Pendulum-v1/dacerf-seed0 \\
        benchmarks/results/intersection-100k/checkpoints/DACERF-Intersection-v0/dacerf-seed0

A checkpoint holds pickles: read only checkpoints you made or trust.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # learning_curves.py


def describe(folder: Path, batch_size: int, seed: int) -> str:
    """One line of statistics for the run saved in ``folder``."""
    import torch as th
    from learning_curves import load_checkpoint

    from sb3_dacerf import DACERF
    from sb3_dacerf.dacerf.policies import MinQActionGradient

    with tempfile.TemporaryDirectory() as tmp:  # a copy: the run may be rewriting its checkpoint meanwhile
        copy = Path(tmp) / "checkpoint"
        shutil.copytree(folder, copy)
        model, _, _ = load_checkpoint(DACERF, copy, "cpu")
    th.manual_seed(seed)
    batch = model.replay_buffer.sample(batch_size, env=model._vec_normalize_env)
    observations, actions = batch.observations, batch.actions
    q_gradient = MinQActionGradient(model.critic, observations)
    gradient = q_gradient(actions)
    q_buffer = q_gradient.min_q(actions)
    columns = [
        f"{folder.parent.name} {folder.name} at {model.num_timesteps} steps",
        f"mean |Q| {q_buffer.abs().mean():.1f}",
        f"|grad_a Q| median {gradient.abs().median():.2f}, p90 {gradient.abs().quantile(0.9):.2f}",
        f"first step (before clipping) {(model.langevin_step_size * gradient).abs().median():.3f}",
    ]
    for label, normalize in (("paper", False), ("normalised", True)):
        th.manual_seed(seed + 1)  # the same Langevin noise for both updates
        model.langevin_normalize_gradient = normalize
        targets = model.langevin_targets(observations, actions)
        gain = (q_gradient.min_q(targets) - q_buffer).mean()
        at_bound = (targets.abs() > 0.999).float().mean()
        columns.append(
            f"{label}: |a*-a_B| median {(targets - actions).abs().median():.3f}, at a bound {at_bound:.0%}, Q gain {gain:.2f}"
        )
    return " | ".join(columns) + f" (a_B at a bound: {(actions.abs() > 0.999).float().mean():.0%})"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoints", nargs="+", type=Path, help="checkpoint folders of learning_curves.py runs")
    parser.add_argument("--batch-size", type=int, default=1024)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    import torch as th

    th.set_num_threads(1)
    for folder in args.checkpoints:
        if not (folder / "model.zip").exists():
            parser.error(f"{folder} is not a checkpoint folder of learning_curves.py (it has no model.zip)")
        print(describe(folder, args.batch_size, args.seed), flush=True)


if __name__ == "__main__":
    main()
