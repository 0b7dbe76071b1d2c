"""
Per-episode reward audit of the driving scenarios: what each reward term adds up to over whole episodes of four
scripted policies, per scenario and traffic density.

Policies (all seeded; none learns):

- ``scripted``: :class:`sb3_dacerf.envs.driving.scripted.ScriptedDriver`, pure pursuit on the reference with speed
  control, braking for the vehicle ahead and yielding to vehicles predicted to cross its path;
- ``idle``: zero increments (the ego keeps its start speed and a straight wheel);
- ``random``: increments drawn uniformly from the action space;
- ``leave``: full steering rate towards the nearest road edge from the first step ("leave the road now").

For each episode: length, outcome (``arrived`` = ``info["is_success"]``, ``collision``, ``off_road`` or
``time_limit`` / ``wrong_exit``), return and the total of every reward term. The markdown table groups the terms
(tracking = lateral + speed + heading, control, comfort, liveness, safety = front + space + side + rear, boundary,
severe = collision + off-road) and gives means over the episodes; ``--csv`` writes every episode and term.

Usage::

    python benchmarks/driving_reward_audit.py --penalty 200 --csv benchmarks/driving_audit/penalty200.csv
    python benchmarks/driving_reward_audit.py --penalty dynamic --csv benchmarks/driving_audit/dynamic.csv
    python benchmarks/driving_reward_audit.py --quick   # one episode per cell, normal density
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from collections import Counter

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import gymnasium as gym
import numpy as np

import sb3_dacerf  # noqa: F401  (registers the environment ids)
from sb3_dacerf.envs.driving.common import REWARD_TERMS
from sb3_dacerf.envs.driving.scripted import ScriptedDriver

SCENARIOS = {"multilane": "DACERF-Multilane-v0", "intersection": "DACERF-Intersection-v0"}
POLICIES = ("scripted", "idle", "random", "leave")
GROUPS = {
    "tracking": ("tracking_lateral", "tracking_speed", "tracking_heading"),
    "control": ("control_acceleration", "control_steering"),
    "comfort": ("comfort_yaw_rate", "comfort_jerk", "comfort_steering_rate"),
    "liveness": ("liveness",),
    "safety": ("safe_front", "safe_space", "safe_side", "safe_rear"),
    "boundary": ("boundary",),
    "severe": ("collision", "off_road", "stalled"),
}


def make_policy(name: str, env: gym.Env, seed: int):
    """A function obs -> action for one episode (call after ``reset``)."""
    low, high = env.action_space.low, env.action_space.high
    if name == "scripted":
        return ScriptedDriver(env)
    if name == "idle":
        return lambda obs: np.zeros(2, dtype=np.float32)
    if name == "random":
        rng = np.random.default_rng(seed)
        return lambda obs: rng.uniform(low, high).astype(np.float32)
    if name == "leave":
        unwrapped = env.unwrapped
        ego = unwrapped.vehicle
        # Steer towards the side whose edge is nearer: compare the clearance 1 m to either side of the ego.
        side = np.array([-np.sin(ego.heading), np.cos(ego.heading)])  # highway-env's +y side of the ego (its right)
        right = unwrapped._road_clearance(ego.position + side) < unwrapped._road_clearance(ego.position - side)
        action = np.array([0.0, high[1] if right else low[1]], dtype=np.float32)
        return lambda obs: action
    raise ValueError(f"Unknown policy {name!r}: expected one of {POLICIES}")


def run_episode(env_id: str, density: str, config: dict, policy: str, seed: int) -> dict:
    env = gym.make(env_id, density=density, config=config)
    obs, _ = env.reset(seed=seed)
    act = make_policy(policy, env, seed)
    terms = dict.fromkeys(REWARD_TERMS, 0.0)
    total, length, done, info = 0.0, 0, False, {}
    while not done:
        obs, reward, terminated, truncated, info = env.step(act(obs))
        total, length, done = total + reward, length + 1, terminated or truncated
        for name, value in info["reward_terms"].items():
            terms[name] += value
    if info["is_success"]:
        outcome = "arrived"
    elif info["collision"]:
        outcome = "collision"
    elif info["off_road"]:
        outcome = "off_road"
    else:
        outcome = "time_limit" if truncated else "wrong_exit"
    route = getattr(env.unwrapped, "route", "")
    env.close()
    return {"return": total, "length": length, "outcome": outcome, "route": route, **terms}


def markdown_table(rows: list[dict]) -> str:
    header = ["scenario", "density", "policy", "episodes", "length", "arrived", "collision", "off road", "return", *GROUPS]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    keys = sorted({(r["scenario"], r["density"], r["policy"]) for r in rows}, key=lambda k: (k[0], k[1], POLICIES.index(k[2])))
    for scenario, density, policy in keys:
        cell = [r for r in rows if (r["scenario"], r["density"], r["policy"]) == (scenario, density, policy)]
        outcomes = Counter(r["outcome"] for r in cell)
        values = [
            scenario,
            density,
            policy,
            str(len(cell)),
            f"{np.mean([r['length'] for r in cell]):.0f}",
            str(outcomes["arrived"]),
            str(outcomes["collision"]),
            str(outcomes["off_road"]),
            f"{np.mean([r['return'] for r in cell]):.0f}",
            *(f"{np.mean([sum(r[t] for t in terms) for r in cell]):.0f}" for terms in GROUPS.values()),
        ]
        lines.append("| " + " | ".join(values) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--penalty", default="dynamic", help="config collision_penalty: 'dynamic' or a number (e.g. 200)")
    parser.add_argument("--episodes", type=int, default=5, help="seeded episodes per scenario, density and policy")
    parser.add_argument("--densities", nargs="+", default=["sparse", "normal", "dense"])
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS))
    parser.add_argument("--policies", nargs="+", default=list(POLICIES), choices=list(POLICIES))
    parser.add_argument("--seed", type=int, default=100, help="seed of the first episode (then +1 per episode)")
    parser.add_argument("--csv", help="write every episode (all reward terms) to this CSV file")
    parser.add_argument("--quick", action="store_true", help="one episode per cell, normal density")
    args = parser.parse_args()
    if args.quick:
        args.episodes, args.densities = 1, ["normal"]
    penalty = args.penalty if args.penalty == "dynamic" else float(args.penalty)

    rows, start = [], time.perf_counter()
    for scenario in args.scenarios:
        for density in args.densities:
            for policy in args.policies:
                for seed in range(args.seed, args.seed + args.episodes):
                    episode = run_episode(SCENARIOS[scenario], density, {"collision_penalty": penalty}, policy, seed)
                    rows.append({"scenario": scenario, "density": density, "policy": policy, "seed": seed, **episode})
    print(
        f"collision_penalty={penalty!r}, {args.episodes} episodes per cell (seeds {args.seed}-{args.seed + args.episodes - 1}), "
        f"{time.perf_counter() - start:.0f} s; means over the episodes, outcomes are counts\n"
    )
    print(markdown_table(rows))
    if args.csv:
        os.makedirs(os.path.dirname(args.csv) or ".", exist_ok=True)
        with open(args.csv, "w", newline="") as file:
            writer = csv.DictWriter(file, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        print(f"\nper-episode rows -> {args.csv}")


if __name__ == "__main__":
    main()
