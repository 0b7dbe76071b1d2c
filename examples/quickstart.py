"""
Train DACER-F on Pendulum-v1, evaluate it, save/load it, and plot its learning curve.

    python examples/quickstart.py                 # 10k steps, about 6 minutes of one CPU core (one torch thread)
    python examples/quickstart.py --timesteps 20000 --out dacerf_quickstart.png
"""

import argparse
import time

import gymnasium as gym
import matplotlib
import torch as th

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_dacerf import DACERF


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--timesteps", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--out", default="dacerf_quickstart.png", help="learning-curve plot")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (small networks gain nothing from more)")
    args = parser.parse_args()
    # On a busy machine, threads of a small network mostly wait on each other: 1 thread was up to 20x faster here
    th.set_num_threads(args.threads)

    env = Monitor(gym.make(args.env))
    # The constructor defaults: entropy regulator on, actor loss balanced by the Langevin gain, SAC's tau
    model = DACERF("MlpPolicy", env, seed=args.seed, verbose=0)
    start = time.perf_counter()
    model.learn(args.timesteps, progress_bar=True)
    train_seconds = time.perf_counter() - start

    model.save("dacerf_quickstart")
    model = DACERF.load("dacerf_quickstart")
    mean_return, std_return = evaluate_policy(model, Monitor(gym.make(args.env)), args.eval_episodes, deterministic=True)
    print(f"{args.env}: trained {args.timesteps} steps in {train_seconds:.0f} s")
    print(f"evaluation over {args.eval_episodes} episodes (deterministic): {mean_return:.1f} +/- {std_return:.1f}")

    returns, lengths = env.get_episode_rewards(), env.get_episode_lengths()
    steps = [sum(lengths[: i + 1]) for i in range(len(lengths))]
    plt.figure(figsize=(6, 3.5))
    plt.plot(steps, returns, marker=".", label="training episodes")
    plt.axhline(mean_return, color="tab:red", linestyle="--", label=f"evaluation: {mean_return:.0f}")
    plt.xlabel("environment steps")
    plt.ylabel("episode return")
    plt.title(f"DACER-F on {args.env}")
    plt.legend()
    plt.tight_layout()
    plt.savefig(args.out, dpi=120)
    print(f"learning curve saved to {args.out}; model saved to dacerf_quickstart.zip")


if __name__ == "__main__":
    main()
