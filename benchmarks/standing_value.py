"""
Is driving worth more than standing still, in the return a learner maximises? Per route of a driving scenario.

For each seeded episode this plays two policies from the same start:

- ``stand``: full braking from the first step, then standing; its value is the discounted return of the first
  ``--stand-steps`` steps plus the mean reward of their last 20 steps continued for ever (what a critic bootstrapped
  at the time limit sees; an episode that ends earlier, e.g. when a stall ends it, counts as it ended);
- ``drive``: :class:`sb3_dacerf.envs.driving.scripted.ScriptedDriver`, or the saved driver ``--driver STEM`` (as
  ``examples/evaluate_driving.py`` loads it), to the end of the episode.

and prints, per density and route, the mean discounted values (``--gamma``), the driver's outcomes, how often it is
worth more than standing, the break-even crash rate: the share of crashes at which an attempt (the driver's arrivals
and crashes mixed in that proportion) is worth as much as standing, and the lowest value of an episode the driver
arrived in (below the severe-event penalty, ending that episode at once was worth more). Episodes start from the
evaluations' starts (``evaluate_driving.evaluation_config``). Any config key can be set with ``--config`` (e.g. the
severe-event penalty)::

    python benchmarks/standing_value.py --episodes 50 --density sparse normal dense
    python benchmarks/standing_value.py --episodes 50 --config '{"collision_penalty": "dynamic", "yield_at_junction": false}'
    python benchmarks/standing_value.py --episodes 50 --driver examples/models/dacerf_intersection_rl
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from collections.abc import Callable

import _checkout  # the repository's sb3_dacerf, not an installed copy
import gymnasium as gym
import numpy as np

import sb3_dacerf  # noqa: F401  (registers the ids)
from sb3_dacerf.envs.driving.scripted import ScriptedDriver

sys.path.append(str(_checkout.ROOT / "examples"))  # evaluate_driving.py
from evaluate_driving import evaluation_config, load_driver

DEFAULT_ENV = "DACERF-Intersection-v0"
BRAKE = np.array([-1.0, 0.0], dtype=np.float32)


def discounted(rewards: list[float], gamma: float) -> float:
    return float(np.sum(np.asarray(rewards) * gamma ** np.arange(len(rewards))))


def standing_value(env: gym.Env, seed: int, gamma: float, steps: int) -> float:
    env.reset(seed=seed)
    rewards, done = [], False
    while not done and len(rewards) < steps:
        _, reward, terminated, truncated, _ = env.step(BRAKE)
        rewards.append(float(reward))
        done = terminated or truncated
    value = discounted(rewards, gamma)
    if not done:  # standing on for ever at the rate of the last 20 steps
        value += gamma ** len(rewards) * float(np.mean(rewards[-20:])) / (1 - gamma)
    return value


def driving_value(env: gym.Env, seed: int, gamma: float, act: Callable[[np.ndarray], np.ndarray] | None) -> tuple[float, dict]:
    """The discounted return of ``act`` (the scripted driver if None) from the start of ``seed``, and the last info."""
    obs, _ = env.reset(seed=seed)
    act = act or ScriptedDriver(env)
    rewards, done, info = [], False, {}
    while not done:
        obs, reward, terminated, truncated, info = env.step(act(obs))
        rewards.append(float(reward))
        done = terminated or truncated
    return discounted(rewards, gamma), info


def break_even(standing: float, arrivals: np.ndarray, crashes: np.ndarray) -> float:
    """The crash rate at which mixing the arrivals' and the crashes' mean values is worth as much as standing."""
    if not len(arrivals) or not len(crashes):
        return float("nan")
    arrive, crash = float(arrivals.mean()), float(crashes.mean())
    return float(np.clip((arrive - standing) / (arrive - crash), 0.0, 1.0)) if arrive > crash else float("nan")


def main(argv: list[str] | None = None) -> dict[tuple[str, str], dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", help=f"the env id (default: {DEFAULT_ENV}; with --driver, its own, which this must match)")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=10_000, help="first evaluation seed")
    parser.add_argument("--gamma", type=float, default=0.99)
    parser.add_argument("--stand-steps", type=int, default=100)
    parser.add_argument("--density", nargs="+", default=["normal"], help="traffic densities, each in turn")
    parser.add_argument("--config", type=json.loads, default={}, help="env config overrides, as JSON")
    parser.add_argument("--driver", help="a saved driver's stem (its .zip, .json, _vecnormalize.json); default: scripted")
    args = parser.parse_args(argv)
    if not 0 < args.gamma < 1:
        parser.error(f"--gamma must be in (0, 1), got {args.gamma}")
    summary = {}
    seeds = f"{args.seed}-{args.seed + args.episodes - 1}"
    print(f"{args.driver or args.env or DEFAULT_ENV}, config {args.config}, gamma {args.gamma}, seeds {seeds}")
    print(
        f"| density | route | episodes | standing | {args.driver or 'scripted driver'} | its arrival / collision "
        "| driving worth more "
        "| break-even crash rate | lowest arrival |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for density in args.density:
        if args.driver:
            driver = load_driver(args.driver, scenario=args.env, density=density, config=args.config)
            env, act = driver.env, driver.act
        else:
            env_id = args.env or DEFAULT_ENV
            env, act = gym.make(env_id, config=evaluation_config(env_id, config=args.config), density=density), None
        rows: dict[str, list[tuple[float, float, bool, bool]]] = defaultdict(list)
        for seed in range(args.seed, args.seed + args.episodes):
            stand = standing_value(env, seed, args.gamma, args.stand_steps)
            drive, info = driving_value(env, seed, args.gamma, act)
            rows[info.get("route", "all")].append((stand, drive, bool(info["is_success"]), bool(info["collision"])))
        for route, values in sorted(rows.items()):
            v = np.asarray(values, dtype=float)
            standing = float(v[:, 0].mean())
            arrivals = v[v[:, 2] == 1, 1]
            threshold = break_even(standing, arrivals, v[v[:, 3] == 1, 1])
            summary[density, route] = dict(
                standing=standing,
                driving=float(v[:, 1].mean()),
                better=float(np.mean(v[:, 1] > v[:, 0])),
                break_even=threshold,
                lowest_arrival=float(arrivals.min()) if len(arrivals) else float("nan"),
            )
            print(
                f"| {density} | {route} | {len(v)} | {standing:,.0f} | {v[:, 1].mean():,.0f} | {v[:, 2].mean():.0%} / "
                f"{v[:, 3].mean():.0%} | {summary[density, route]['better']:.0%} | {threshold:.0%} | "
                f"{summary[density, route]['lowest_arrival']:,.0f} |",
                flush=True,
            )
    return summary


if __name__ == "__main__":
    main()
