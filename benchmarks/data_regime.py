"""
What a data regime costs: environment steps per second and gradient steps per second of one variant trained at S
environment steps per gradient step (``--steps-per-gradient`` of ``learning_curves.py`` and ``train_driving.py``),
and what a run of ``--budget-hours`` affords at each S.

One model per S (seed ``--seed``, one environment, ``learning_curves.new_model``) is warmed up with
``--learning-starts`` random transitions, then trained in ``--rounds`` blocks of ``--gradient-steps / --rounds``
gradient steps each, the values of S in turn, in a new random order each round, in this process. The CPU time of
``model.train`` is the gradient steps' cost; the rest of ``model.learn`` (the environment, the policy's actions, the
replay buffer) is the sampling cost. CPU time of this one process (one torch thread): the cost on one core, less
disturbed by other processes than the wall time, which is given too. The projection divides the budget by the CPU
time per gradient step (S sampling steps and one update): what one idle core affords; and by the wall time per gradient
step: what this machine afforded at the load of the measurement.

    python benchmarks/data_regime.py --env DACERF-Multilane-v0 --variant dacerf-paper --steps-per-gradient 1 4 16
    python benchmarks/data_regime.py --quick                                  # Pendulum-v1, a few seconds
"""

from __future__ import annotations

import argparse
import random
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # learning_curves.py and timing.py


def measure(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Train one model per S in alternating blocks; return one row of counts and times per S."""
    import torch as th
    from learning_curves import VARIANTS, algorithm_class, new_model

    from sb3_dacerf.common.regime import parse_steps_per_gradient, transitions_per_rollout
    from sb3_dacerf.dacerf import PAPER_HYPERPARAMETERS

    th.set_num_threads(1)
    name, kwargs = VARIANTS[args.variant]
    kwargs = dict(kwargs)
    if kwargs.pop("paper", False):
        kwargs = {**PAPER_HYPERPARAMETERS, **kwargs}
    kwargs["learning_starts"] = args.learning_starts
    block = args.gradient_steps // args.rounds
    runs: dict[str, dict[str, Any]] = {}
    for steps in args.steps_per_gradient:
        job = dict(env=args.env, env_kwargs={}, seed=args.seed, device="cpu", vec_normalize=False, steps_per_gradient=steps)
        model = new_model(job, algorithm_class(name), kwargs)
        times = dict(train=0.0)

        def timed_train(gradient_steps: int, batch_size: int, model: Any = model, times: dict = times) -> None:
            start = time.process_time()
            type(model).train(model, gradient_steps=gradient_steps, batch_size=batch_size)
            times["train"] += time.process_time() - start

        model.train = timed_train  # type: ignore[method-assign]
        with warnings.catch_warnings():  # the package's warning that learn() made no gradient step: not yet, on purpose
            warnings.simplefilter("ignore", UserWarning)
            model.learn(args.learning_starts)  # random transitions (and a first update when S does not divide them)
        times["train"] = 0.0  # the counts and times below start here
        # whole rollouts: the block's transitions rounded up to a multiple of train_freq * n_envs
        rollout = transitions_per_rollout(steps, 1)
        transitions = -(-int(block * parse_steps_per_gradient(steps)) // rollout) * rollout
        start = dict(env_steps=model.num_timesteps, gradient_steps=model._n_updates)
        runs[steps] = dict(model=model, times=times, transitions=transitions, cpu=0.0, wall=0.0, start=start)
    order = list(runs)
    for _ in range(args.rounds):
        random.shuffle(order)
        for steps in order:
            run = runs[steps]
            cpu, wall = time.process_time(), time.perf_counter()
            run["model"].learn(run["transitions"], reset_num_timesteps=False)
            run["cpu"] += time.process_time() - cpu
            run["wall"] += time.perf_counter() - wall
    rows = []
    for steps, run in runs.items():
        model, train = run["model"], run["times"]["train"]
        env_steps = model.num_timesteps - run["start"]["env_steps"]
        updates = model._n_updates - run["start"]["gradient_steps"]
        sampling = run["cpu"] - train
        per_update = run["cpu"] / updates
        budget = args.budget_hours * 3600
        rows.append(
            dict(
                steps_per_gradient=steps,
                env_steps=env_steps,
                gradient_steps=updates,
                env_steps_per_second=env_steps / sampling,
                gradient_steps_per_second=updates / train,
                cpu_ms_per_gradient_step=1000 * per_update,
                wall_ms_per_gradient_step=1000 * run["wall"] / updates,
                budget_gradient_steps=budget / per_update,
                budget_env_steps=budget / per_update * float(parse_steps_per_gradient(steps)),
                budget_gradient_steps_wall=budget * updates / run["wall"],
                budget_env_steps_wall=budget * updates / run["wall"] * float(parse_steps_per_gradient(steps)),
            )
        )
        model.get_env().close()
    return rows


def table(rows: list[dict[str, Any]], budget_hours: float) -> str:
    """The rows as a markdown table."""
    lines = [
        f"| S | env steps | gradient steps | env steps/s (sampling CPU) | gradient steps/s (train CPU) | CPU ms per "
        f"gradient step | wall ms per gradient step | in {budget_hours:g} h of one core: gradient steps | env steps | "
        f"in {budget_hours:g} h of wall time at this load: gradient steps | env steps |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['steps_per_gradient']} | {row['env_steps']} | {row['gradient_steps']} | "
            f"{row['env_steps_per_second']:.0f} | {row['gradient_steps_per_second']:.1f} | "
            f"{row['cpu_ms_per_gradient_step']:.1f} | {row['wall_ms_per_gradient_step']:.1f} | "
            f"{row['budget_gradient_steps']:,.0f} | {row['budget_env_steps']:,.0f} | "
            f"{row['budget_gradient_steps_wall']:,.0f} | {row['budget_env_steps_wall']:,.0f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    from learning_curves import VARIANTS
    from timing import load_average, machine_name

    from sb3_dacerf.common.regime import steps_per_gradient_kwargs

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="DACERF-Multilane-v0")
    parser.add_argument("--variant", default="dacerf-paper", help=f"one of learning_curves.py's: {', '.join(VARIANTS)}")
    parser.add_argument("--steps-per-gradient", nargs="+", default=["1", "4", "16"], help="the values of S compared")
    parser.add_argument("--gradient-steps", type=int, default=2_000, help="gradient steps per S, over all rounds")
    parser.add_argument("--rounds", type=int, default=4, help="blocks per S, the values of S alternating")
    parser.add_argument("--learning-starts", type=int, default=1_000, help="random transitions before the first update")
    parser.add_argument("--budget-hours", type=float, default=2.5, help="the run length the projection is for")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="Pendulum-v1, 40 gradient steps per S: checks the pipeline")
    args = parser.parse_args(argv)
    if args.quick:
        args.env, args.gradient_steps, args.rounds, args.learning_starts = "Pendulum-v1", 40, 2, 100
    if args.variant not in VARIANTS:
        parser.error(f"--variant {args.variant}: choose one of {', '.join(VARIANTS)}")
    if min(args.gradient_steps, args.rounds, args.learning_starts) < 1 or args.gradient_steps < args.rounds:
        parser.error("--gradient-steps, --rounds and --learning-starts must be at least 1, --gradient-steps >= --rounds")
    own = {"train_freq", "gradient_steps"} & set(VARIANTS[args.variant][1])
    if own:
        parser.error(f"--variant {args.variant} sets {sorted(own)} itself: choose a variant that leaves them to S")
    for steps in args.steps_per_gradient:
        try:
            steps_per_gradient_kwargs(steps, 1)
        except ValueError as error:
            parser.error(f"--steps-per-gradient: {error}")
    rows = measure(args)
    print(f"\n{args.env}, {args.variant}, seed {args.seed}, one environment, {machine_name()}, {load_average()}")
    print("command: python benchmarks/data_regime.py " + " ".join(argv if argv is not None else sys.argv[1:]) + "\n")
    print(table(rows, args.budget_hours))
    return rows


if __name__ == "__main__":
    main()
