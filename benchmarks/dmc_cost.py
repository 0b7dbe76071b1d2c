"""
What one environment step of a DMC learning run costs on this machine, by part: the simulator, the policy's action
(inference) and the gradient step, for each learner with its defaults on one torch thread. The cost of a run of E
environment steps at S steps per gradient step is E * (environment + inference + update / S).

    python benchmarks/dmc_cost.py [--envs DMC-humanoid-stand-v0 DMC-dog-stand-v0] [--algorithms DACERF SAC DSAC DACER]
                                  [--updates 200] [--steps 2000]
"""

import argparse
import time

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import SAC

import sb3_dacerf
from sb3_dacerf import DACER, DACERF, DSAC

ALGORITHMS = {"DACERF": DACERF, "DACER": DACER, "DSAC": DSAC, "SAC": SAC}


def milliseconds(function, repeats: int) -> float:
    start = time.perf_counter()
    for _ in range(repeats):
        function()
    return 1000 * (time.perf_counter() - start) / repeats


def costs(env_id: str, algorithm: str, updates: int, steps: int) -> dict[str, float]:
    """Milliseconds per environment step (random actions), per action (``predict``) and per gradient step."""
    env = gym.make(env_id)
    env.reset(seed=0)
    actions = iter(np.random.default_rng(0).uniform(-1, 1, size=(steps, *env.action_space.shape)).astype(np.float32))

    def step() -> None:
        _, _, terminated, truncated, _ = env.step(next(actions))
        if terminated or truncated:
            env.reset()

    environment = milliseconds(step, steps)
    model = ALGORITHMS[algorithm]("MlpPolicy", env_id, learning_starts=0, seed=0)
    model.learn(1_000)  # fills the buffer with 1,000 transitions and makes as many gradient steps
    observation = model.get_env().reset()
    inference = milliseconds(lambda: model.predict(observation, deterministic=False), 500)
    update = milliseconds(lambda: model.train(gradient_steps=1, batch_size=model.batch_size), updates)
    return dict(environment=environment, inference=inference, update=update)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["DMC-humanoid-stand-v0", "DMC-dog-stand-v0"])
    parser.add_argument("--algorithms", nargs="+", default=list(ALGORITHMS), choices=list(ALGORITHMS))
    parser.add_argument("--updates", type=int, default=200)
    parser.add_argument("--steps", type=int, default=2_000)
    parser.add_argument("--budget", type=int, default=500_000, help="environment steps of the hours columns")
    args = parser.parse_args()
    th.set_num_threads(1)
    assert sb3_dacerf
    print(f"| task | learner | env ms | action ms | update ms | hours per {args.budget:,} steps at S = 1 / 2 / 4 |")
    print("|---|---|---|---|---|---|")
    for env_id in args.envs:
        for algorithm in args.algorithms:
            cost = costs(env_id, algorithm, args.updates, args.steps)
            hours = [args.budget * (cost["environment"] + cost["inference"] + cost["update"] / s) / 3.6e6 for s in (1, 2, 4)]
            print(
                f"| {env_id} | {algorithm} | {cost['environment']:.2f} | {cost['inference']:.2f} | {cost['update']:.1f} | "
                + " / ".join(f"{h:.1f}" for h in hours)
                + " |",
                flush=True,
            )


if __name__ == "__main__":
    main()
