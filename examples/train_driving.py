"""
Train DACER-F (or, for comparison, DACER, DSAC or SAC: ``--algo``) on the paper's driving scenarios, print progress
(episodes, return, arrival, collision and off-road rates) while it trains, and report, over deterministic evaluation
episodes, the paper's metrics: total average return (TAR), arrival rate (``info["is_success"]``: destination reached
at the intersection, time limit reached safely on the highway), collision and off-road rates.

    python examples/train_driving.py --timesteps 2000 --eval-episodes 5       # short smoke run of both scenarios
    python examples/train_driving.py --env multilane --timesteps 100000 --n-envs 2 --vec-normalize --save runs/dacerf
    python examples/train_driving.py --env multilane --density random --vec-normalize masked --timesteps 100000  # all densities
    python examples/train_driving.py --load runs/dacerf_multilane --timesteps 50000 --save runs/dacerf   # resume
    python examples/evaluate_driving.py runs/dacerf_multilane.zip --episodes 50                        # evaluate

``--density random`` (or ``sparse,normal``, or a JSON dict of weights) draws each training episode's traffic density
from its reset seed, and the final evaluation's too; ``--vec-normalize masked`` normalises the observations with
``sb3_dacerf.common.vec_normalize.MaskedVecNormalize``, whose empty vehicle rows stay zeros whatever the number of
vehicles (``--vec-normalize`` alone: SB3's ``VecNormalize``).
At the intersection half the training episodes start in the traffic flow (``reference_start_probability``, 0.5 by
default), and the final evaluation starts from the standard starts (``evaluate_driving.evaluation_config``).

``--save NAME`` writes ``NAME_<scenario>.zip`` (the model), ``NAME_<scenario>.json`` (env id, density, config,
algorithm: what ``evaluate_driving.py`` and ``--load`` read), ``NAME_<scenario>_vecnormalize.json`` with
``--vec-normalize`` and ``NAME_<scenario>_replay_buffer.pkl`` with ``--save-replay-buffer``. ``--load`` resumes the
step count, the normalisation statistics and, if saved, the replay buffer (without it, training restarts from an
empty buffer and waits ``--learning-starts`` steps again).

Hyper-parameters: the algorithm's constructor defaults (for DACERF those of benchmarks/learning.md: entropy
regulator on, actor loss weighted by the Langevin gain, lr 3e-4, batch 256, τ = 0.005); DACER and DSAC with their
authors' defaults, SAC with SB3's (``--algo dacer``, ``dsac``, ``sac``); the driving results
(docs/benchmarks/driving.md) add ``--steps-per-gradient 16 --vec-normalize masked``. ``--paper`` selects the paper's
Table II values (learning rate 1e-4, replay batch 512, RAD, γ = 0.99, τ = 0.001, policy delay 3, Langevin η = 0.03,
α = 0.01, 20 steps, no added exploration noise), of which DACER, DSAC and SAC take the learning rate, batch, τ and
data regime. The paper trains 5e5 iterations.

Data regime: by default every step of the ``--n-envs`` environments is followed by one gradient step (``--n-envs``
transitions per gradient step). ``--steps-per-gradient S`` makes it S transitions per gradient step, as the paper's
trainer (GOPS) collects its "sample batch size" (200) per iteration: S >= 1 a multiple of ``--n-envs``, or 1/G for G
gradient steps per transition (``sb3_dacerf.common.regime``; the "Data regime" guide works the paper's table out).
Progress lines and the final line count both environment steps and gradient steps.

    python examples/train_driving.py --env multilane --timesteps 200000 --steps-per-gradient 20 --n-envs 2 --vec-normalize
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import deque

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

import sb3_dacerf  # noqa: F401  (registers the environment ids)
from sb3_dacerf.common.persistence import load_vec_normalize, safe_save, save_vec_normalize
from sb3_dacerf.common.regime import steps_per_gradient_kwargs
from sb3_dacerf.common.vec_normalize import MaskedVecNormalize
from sb3_dacerf.dacerf import PAPER_HYPERPARAMETERS
from sb3_dacerf.envs.driving.common.observation import vehicle_rows

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from evaluate_driving import (
    ALGORITHMS,
    SCENARIOS,
    evaluate,
    evaluation_config,
    format_results,
    load_algorithm,
    model_paths,
    parse_density,
    policy_act,
)


class DrivingProgress(BaseCallback):
    """
    Print, every ``interval`` environment steps, the training episodes' mean return, arrival, collision and off-road
    rates and length over the last ``window`` episodes.
    """

    def __init__(self, total: int, interval: int = 1_000, window: int = 20) -> None:
        super().__init__()
        self.total, self.interval = total, interval
        self.episodes = deque(maxlen=window)
        self.count, self.start, self.next_print = 0, time.perf_counter(), interval

    def _on_training_start(self) -> None:
        self.first_step, self.first_update, self.start = self.num_timesteps, self.model._n_updates, time.perf_counter()

    def _on_step(self) -> bool:
        for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
            if done and "episode" in info:
                self.episodes.append(
                    (info["episode"]["r"], info["episode"]["l"], info["is_success"], info["collision"], info["off_road"])
                )
                self.count += 1
        steps = self.num_timesteps - self.first_step
        if steps >= self.next_print:
            self.next_print += self.interval
            seconds = time.perf_counter() - self.start
            updates = self.model._n_updates - self.first_update
            line = f"  {steps}/{self.total} steps, {steps / seconds:.0f} steps/s, {updates} gradient steps"
            line += f" ({updates / seconds:.1f}/s)"
            if self.episodes:
                r, length, arrived, collided, off_road = np.array(self.episodes, dtype=np.float64).T
                line += (
                    f", {self.count} episodes; last {len(self.episodes)}: return {r.mean():.0f}, length {length.mean():.0f}, "
                    f"arrival {arrived.mean():.0%}, collision {collided.mean():.0%}, off-road {off_road.mean():.0%}"
                )
            print(line, flush=True)
        return True


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", choices=["all", *SCENARIOS], help="scenario(s) to train on (default: all; with --load its own)")
    parser.add_argument("--algo", choices=list(ALGORITHMS), help="default: dacerf (with --load: the saved model's)")
    parser.add_argument("--timesteps", type=int, default=20_000, help="training steps per scenario (more steps with --load)")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument(
        "--density",
        type=parse_density,
        default="normal",
        help="traffic density: sparse, normal, dense, or one drawn per episode from its reset seed: random (the three "
        "alike), a list 'sparse,normal' or a JSON dict of weights '{\"sparse\": 1, \"dense\": 2}'",
    )
    parser.add_argument("--config", type=json.loads, default={}, help="env config overrides as JSON, e.g. '{\"duration\": 20}'")
    parser.add_argument("--learning-starts", type=int, default=1_000, help="random steps before the first update")
    parser.add_argument("--batch-size", type=int, help="replay batch size (default: the algorithm's, 256; the paper's 512)")
    parser.add_argument(
        "--paper",
        action="store_true",
        help="the paper's training hyper-parameters (sb3_dacerf.dacerf.PAPER_HYPERPARAMETERS: lr 1e-4, batch 512, RAD, "
        "tau 0.001, no added exploration noise, 200 transitions per gradient step over all --n-envs envs unless "
        "--steps-per-gradient says otherwise; DACER, DSAC and SAC get the same lr, batch, tau and data regime) instead of the "
        "constructor defaults",
    )
    parser.add_argument("--n-envs", type=int, default=1, help="parallel training envs (SubprocVecEnv when > 1)")
    parser.add_argument(
        "--vec-env",
        choices=["dummy", "subproc"],
        help="how the --n-envs envs are stepped: in this process (DummyVecEnv) or one process each (SubprocVecEnv, one "
        "core each); default: subproc when --n-envs > 1",
    )
    parser.add_argument(
        "--steps-per-gradient",
        help="the data regime: S environment steps (transitions) per gradient step, a multiple of --n-envs (the "
        "paper's sample batch size, 200), or 1/G for G gradient steps per transition; sets train_freq and "
        "gradient_steps (default: one gradient step per step of the --n-envs envs; with --load, the saved model's)",
    )
    parser.add_argument(
        "--vec-normalize",
        nargs="?",
        const="plain",
        choices=["plain", "masked"],
        help="normalise observations (rewards kept): with SB3's VecNormalize, or 'masked': with "
        "sb3_dacerf.common.vec_normalize.MaskedVecNormalize, whose empty vehicle rows stay zeros at any density",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", help="save each model to <SAVE>_<scenario>.zip (+ .json, _vecnormalize.json)")
    parser.add_argument("--save-replay-buffer", action="store_true", help="also save the replay buffer (for --load)")
    parser.add_argument("--load", help="resume training from a model saved with --save (path with or without .zip)")
    parser.add_argument("--log-interval", type=int, default=1_000, help="print training progress every N steps (0: never)")
    parser.add_argument(
        "--torch-threads",
        type=int,
        default=1,
        help="torch CPU threads (measured here on a loaded 2-core machine: 1 thread was 7-30x faster per update than 2)",
    )
    return parser


def resume_settings(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict[str, str]:
    """
    Check ``--load`` against the other options and fill in, from the saved model's ``.json``, the settings that were not
    given (scenario, algorithm, density, config, observation normalisation).

    :return: the saved model's paths (see ``model_paths``)
    """
    load_paths = model_paths(args.load)
    if not os.path.isfile(load_paths["model"]):
        parser.error(f"--load: no model file {load_paths['model']!r}; pass the NAME_<scenario>.zip written by --save")
    metadata = {}
    if os.path.isfile(load_paths["metadata"]):
        with open(load_paths["metadata"]) as file:
            metadata = json.load(file)
    trained = {v: k for k, v in SCENARIOS.items()}.get(metadata.get("env_id"))
    if args.env not in (None, trained) or (trained is None and args.env in (None, "all")):
        parser.error(
            f"--load: {args.load} was trained on {trained or 'an unknown scenario'}: "
            f"pass --env {trained or 'multilane or --env intersection'}"
        )
    if args.algo and metadata.get("algo", args.algo) != args.algo:
        parser.error(f"--load: {args.load} is a {metadata['algo']} model: pass --algo {metadata['algo']} or leave it out")
    args.algo = args.algo or metadata.get("algo")
    args.env = trained or args.env
    args.density, args.config = metadata.get("density", args.density), {**metadata.get("config", {}), **args.config}
    args.vec_normalize = args.vec_normalize or ("plain" if os.path.isfile(load_paths["vec_normalize"]) else None)
    return load_paths


def check_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse settings that cannot work, with argparse's usage message and exit status 2."""
    if args.n_envs < 1:
        parser.error(f"--n-envs must be >= 1, got {args.n_envs}")
    if args.density == "all":
        parser.error(
            "--density all evaluates at each density in turn (evaluate_driving.py): to train on all of them, "
            "pass --density random, which draws one per episode"
        )
    if args.steps_per_gradient is not None:
        try:
            steps_per_gradient_kwargs(args.steps_per_gradient, args.n_envs)
        except ValueError as error:
            parser.error(f"--steps-per-gradient / --n-envs: {error}")


def algorithm_kwargs(args: argparse.Namespace) -> dict:
    """The keyword arguments of a new model: the constructor defaults (benchmarks/learning.md) or the paper's Table II
    values with ``--paper``, and what the other options ask for."""
    kwargs: dict = {}
    if args.paper:
        # what DACER, DSAC and SAC take of the paper's settings: the optimiser step, batch, target update and data regime
        shared = ("learning_rate", "batch_size", "tau", "train_freq", "gradient_steps")
        kwargs = {k: v for k, v in PAPER_HYPERPARAMETERS.items() if args.algo == "dacerf" or k in shared}
        # the paper's 200 transitions per gradient step, over all the --n-envs environments
        kwargs.update(steps_per_gradient_kwargs(PAPER_HYPERPARAMETERS["train_freq"], args.n_envs))
    if args.batch_size is not None:
        kwargs["batch_size"] = args.batch_size
    if args.steps_per_gradient is not None:
        kwargs.update(steps_per_gradient_kwargs(args.steps_per_gradient, args.n_envs))
    return kwargs


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    check_args(parser, args)
    torch.set_num_threads(args.torch_threads)
    load_paths = resume_settings(parser, args) if args.load else None

    args.algo = args.algo or "dacerf"
    algo_class = load_algorithm(args.algo)
    algo_kwargs = algorithm_kwargs(args)

    vec_env = args.vec_env or ("subproc" if args.n_envs > 1 else "dummy")
    scenarios = SCENARIOS if args.env in (None, "all") else {args.env: SCENARIOS[args.env]}
    for name, env_id in scenarios.items():
        # "module:id" makes spawned SubprocVecEnv workers import (and so register) the package.
        env = make_vec_env(
            f"sb3_dacerf:{env_id}",
            n_envs=args.n_envs,
            seed=args.seed,
            env_kwargs={"density": args.density, "config": args.config},
            vec_env_cls=SubprocVecEnv if vec_env == "subproc" else DummyVecEnv,
        )
        if load_paths and os.path.isfile(load_paths["vec_normalize"]):
            env = load_vec_normalize(load_paths["vec_normalize"], env)
        elif args.vec_normalize == "masked":
            rows = vehicle_rows(env.get_attr("config")[0])
            env = MaskedVecNormalize(env, rows=rows, norm_obs=True, norm_reward=False)
        elif args.vec_normalize:
            env = VecNormalize(env, norm_obs=True, norm_reward=False)
        if load_paths:
            # --steps-per-gradient replaces the saved model's train_freq and gradient_steps
            regime = steps_per_gradient_kwargs(args.steps_per_gradient, args.n_envs) if args.steps_per_gradient else {}
            model = algo_class.load(load_paths["model"], env=env, device="cpu", **regime)
            replay_path = load_paths["model"][:-4] + "_replay_buffer.pkl"
            if os.path.isfile(replay_path):
                model.load_replay_buffer(replay_path)
            print(f"{env_id}: resumed {load_paths['model']} at {model.num_timesteps} steps", flush=True)
        else:
            model = algo_class("MlpPolicy", env, learning_starts=args.learning_starts, seed=args.seed, verbose=0, **algo_kwargs)
        print(
            f"{env_id} ({args.density}), {args.algo}, training {args.timesteps} steps on {args.n_envs} env(s)"
            + (", observations normalised" if isinstance(env, VecNormalize) else "")
            + (" (MaskedVecNormalize)" if isinstance(env, MaskedVecNormalize) else "")
            + f", {model.gradient_steps} gradient step(s) every {model.train_freq.frequency * args.n_envs} steps",
            flush=True,
        )
        callback = DrivingProgress(args.timesteps, args.log_interval) if args.log_interval > 0 else None
        start, first_update = time.perf_counter(), model._n_updates
        model.learn(args.timesteps, callback=callback, reset_num_timesteps=load_paths is None)
        train_seconds = time.perf_counter() - start
        vec_normalize = env if isinstance(env, VecNormalize) else None
        if args.save:
            paths = model_paths(f"{args.save}_{name}")
            os.makedirs(os.path.dirname(paths["model"]) or ".", exist_ok=True)
            safe_save(model, paths["model"])
            with open(paths["metadata"], "w") as file:
                json.dump({"env_id": env_id, "density": args.density, "config": args.config, "algo": args.algo}, file)
            if vec_normalize is not None:
                save_vec_normalize(vec_normalize, paths["vec_normalize"])
            if args.save_replay_buffer:
                model.save_replay_buffer(paths["model"][:-4] + "_replay_buffer.pkl")
            print(f"saved {paths['model']}" + (f" and {paths['vec_normalize']}" if vec_normalize is not None else ""), flush=True)
        if vec_normalize is not None:
            vec_normalize.training = False
        # Evaluation episodes use seeds the training resets did not (training resets are seeded from --seed), from
        # the standard starts (evaluation_config)
        eval_env = gym.make(env_id, density=args.density, config=evaluation_config(env_id, args.config))
        results = evaluate(policy_act(model, vec_normalize), eval_env, args.eval_episodes, seed=10_000 + args.seed)
        print(
            f"trained {model.num_timesteps} steps in total ({model._n_updates} gradient steps), {train_seconds:.0f} s "
            f"this run ({model._n_updates - first_update} gradient steps); " + format_results(env_id, results, args.eval_episodes)
        )
        env.close()


if __name__ == "__main__":
    main()
