"""
The collisions at each traffic density that braking does not avoid, and which of them a lane chosen in hindsight does.

For each scenario and density it drives the same seeds twice: with the scripted driver
(:class:`~sb3_dacerf.envs.driving.scripted.ScriptedDriver`), and with the same driver commanding the ego's
strongest braking (the low end of the env's ``acceleration_range``, -0.8 m/s² as in the paper) from the first
step to the last, its steering unchanged (it follows its reference path, which may change lanes). Braking at the limit
from the start keeps the ego as far back as it can be at every moment, so an episode where that ego still runs into a
vehicle ahead is one that braking along the reference does not win (the traffic reacts to the ego, so this is strong
evidence, not a proof). On the multi-lane highway it then searches, for each such episode, the lanes the ego could
have taken instead: from step k (0, 5, ..., 55) on, follow lane L (any of them, its own included) braking at the limit
or holding its speed (braking for a vehicle close ahead in that lane). An episode one of these completes without a
collision is one a driver that knew the future could win; the others no driver of the search wins (a search, not a
proof that no driver could). For the braking ego's collisions it prints where the other vehicle was (ahead of the
ego's centre, or behind it / alongside), when the collision came, the closing speed at contact (the ego's speed along
its heading minus the other's; with the ego's own speed, whether it ran into the other or stood while the other ran
into it) and the other vehicle's hardest braking over the 3 s before it, against the ego's limit (the traffic's IDM
brakes at up to ``IDMVehicle.ACC_MAX``, 6 m/s²).

Usage::

    python benchmarks/driving_collision_floor.py --episodes 50 --seed 40000
    python benchmarks/driving_collision_floor.py --env multilane --densities dense --episodes 10
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from typing import Any

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import gymnasium as gym
import numpy as np

from sb3_dacerf.envs.driving import register_driving_envs
from sb3_dacerf.envs.driving.density import DENSITIES as DENSITY_NAMES
from sb3_dacerf.envs.driving.scripted import ScriptedDriver

ENV_IDS = {"multilane": "DACERF-Multilane-v0", "intersection": "DACERF-Intersection-v0"}
EN_DASH = "\u2013"
LOOKBACK = 3.0
"""Seconds before a collision over which the other vehicle's hardest braking is taken."""


class BrakingDriver(ScriptedDriver):
    """The scripted driver's steering, with the ego's strongest braking at every step."""

    def _acceleration(self, waypoints: np.ndarray, vehicles: np.ndarray, v_x: float, reference_speed: float) -> float:
        return float(self._unwrapped.config["acceleration_range"][0])


class LaneDriver(BrakingDriver):
    """
    The braking driver until a step, then pure pursuit on a lane of the multi-lane road (read from the simulator),
    braking at the limit (``hold=False``) or holding the speed unless a vehicle is close ahead in that lane.
    """

    def __init__(self, env: gym.Env, lane_id: int, from_step: int, hold: bool):
        super().__init__(env)
        self.lane_id, self.from_step, self.hold, self.steps = lane_id, from_step, hold, 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        self.steps += 1
        if self.steps <= self.from_step:
            return super().__call__(obs)
        unwrapped, ego = self._unwrapped, self._unwrapped.vehicle
        lane = unwrapped.road.network.get_lane(("0", "1", self.lane_id))
        s, _ = lane.local_coordinates(ego.position)
        target = lane.position(s + max(6.0, ego.speed), 0.0) - ego.position
        cos, sin = np.cos(ego.heading), np.sin(ego.heading)
        waypoints = np.array([[0.0, 0.0], [cos * target[0] + sin * target[1], -sin * target[0] + cos * target[1]]])
        braking = float(unwrapped.config["acceleration_range"][0])
        acceleration = braking
        if self.hold:
            ahead = [lane.local_coordinates(v.position) for v in unwrapped.road.vehicles if v is not ego]
            close = any(abs(lateral) < 2.5 and 0 < s_v - s < 2.0 * ego.speed + 8.0 for s_v, lateral in ahead)
            acceleration = braking if close else 0.0
        desired = np.array([acceleration, self._steering(waypoints, 1.0)])
        return unwrapped.action_type.command_action(desired).astype(np.float32)


def drive(env: gym.Env, driver: ScriptedDriver, seed: int, speeds: list[dict[int, float]] | None = None) -> dict:
    """
    One episode of ``driver`` from ``reset(seed=seed)``; its last ``info``.

    :param speeds: if given, gets per step the speed of every vehicle on the road, by ``id``
    """
    obs, _ = env.reset(seed=seed)
    done, info = False, {}
    while not done:
        obs, _, terminated, truncated, info = env.step(driver(obs))
        done = terminated or truncated
        if speeds is not None:
            speeds.append({id(v): v.speed for v in env.unwrapped.road.vehicles})
    return info


def evasion(env: gym.Env, seed: int) -> tuple[int, int, bool] | None:
    """
    The first lane change (from step, lane, hold) of :class:`LaneDriver`'s search that completes the multi-lane
    episode of this seed without a collision, or ``None``.
    """
    for from_step in range(0, 60, 5):
        for lane_id in range(env.unwrapped.config["lanes_count"]):
            for hold in (False, True):
                if drive(env, LaneDriver(env, lane_id, from_step, hold), seed)["is_success"]:
                    return from_step, lane_id, hold
    return None


def run(env_id: str, density: str, braking: bool, episodes: int, seed: int) -> dict[str, Any]:
    """
    Drive ``episodes`` episodes from ``seed`` on.

    :return: arrival and collision rates, ``limit`` (the ego's strongest braking, m/s², positive), and one record per
        collision: ``ahead`` (the other vehicle's centre in
        front of the ego's), ``time`` [s], ``ego_speed`` and ``closing_speed`` [m/s] and ``other_braking`` (its
        hardest deceleration over the last ``LOOKBACK`` seconds, m/s², positive)
    """
    env = gym.make(env_id, density=density)
    unwrapped = env.unwrapped
    driver = (BrakingDriver if braking else ScriptedDriver)(env)
    frequency = unwrapped.config["policy_frequency"]
    window = round(LOOKBACK * frequency)
    arrivals, collisions, records = 0, 0, []
    for episode in range(episodes):
        speeds: list[dict[int, float]] = []
        info = drive(env, driver, seed + episode, speeds)
        arrivals += bool(info["is_success"])
        if not info["collision"]:
            continue
        collisions += 1
        ego = unwrapped.vehicle
        others = [v for v in unwrapped.road.vehicles if v is not ego]
        crashed = [v for v in others if v.crashed] or others
        other = min(crashed, key=lambda v: float(np.linalg.norm(v.position - ego.position)))
        heading = np.array([np.cos(ego.heading), np.sin(ego.heading)])
        history = [step[id(other)] for step in speeds[-window - 1 :] if id(other) in step]
        braking_rates = -np.diff(history) * frequency if len(history) > 1 else np.zeros(1)
        records.append(
            {
                "seed": seed + episode,
                "ahead": float((other.position - ego.position) @ heading) > 0,
                "time": len(speeds) / frequency,
                "ego_speed": float(ego.speed),
                "closing_speed": float((ego.velocity - other.velocity) @ heading),
                "other_braking": float(max(braking_rates.max(), 0.0)),
            }
        )
    limit = -float(unwrapped.config["acceleration_range"][0])
    env.close()
    return {"arrival_rate": arrivals / episodes, "collision_rate": collisions / episodes, "limit": limit, "collisions": records}


def summary(records: list[dict[str, Any]], limit: float) -> str:
    """Table cells describing the collisions of the braking ego."""
    if not records:
        return "— | — | — | — | — | —"
    ahead = sum(r["ahead"] for r in records)
    times = np.array([r["time"] for r in records])
    ego_speeds = np.array([r["ego_speed"] for r in records])
    closing = np.array([r["closing_speed"] for r in records if r["ahead"]])
    braking = np.array([r["other_braking"] for r in records if r["ahead"]])
    harder = int(np.sum(braking > limit + 1e-6))
    cells = [f"{ahead} of {len(records)}", *map(_spread, (times, ego_speeds, closing, braking)), f"{harder} of {ahead}"]
    return " | ".join(cells)


def _spread(values: np.ndarray) -> str:
    """Median (range) of some values, or a dash for none."""
    if not len(values):
        return "—"
    median, low, high = (round(float(v), 1) + 0.0 for v in (np.median(values), values.min(), values.max()))  # no "-0.0"
    return f"{median:.1f} ({low:.1f}{EN_DASH}{high:.1f})"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", choices=["all", *ENV_IDS], default="all", help="the scenario(s) to drive")
    parser.add_argument("--densities", default=",".join(DENSITY_NAMES), help=f"comma-separated, of {', '.join(DENSITY_NAMES)}")
    parser.add_argument("--episodes", type=int, default=50, help="episodes per scenario, density and driver")
    parser.add_argument("--seed", type=int, default=40_000, help="seed of the first episode of every evaluation")
    args = parser.parse_args(argv)
    densities = [d.strip() for d in args.densities.split(",") if d.strip()]
    unknown = [d for d in densities if d not in DENSITY_NAMES]
    if unknown or not densities:
        parser.error(f"--densities {args.densities!r}: pass a comma-separated list of {', '.join(DENSITY_NAMES)}")
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    register_driving_envs()
    started = time.time()
    command = "python benchmarks/driving_collision_floor.py " + " ".join(argv if argv is not None else sys.argv[1:])
    lines = [
        "| scenario | density | scripted driver: arrival, collision | braking at the limit: arrival, collision "
        "| its collisions with a vehicle ahead | time of collision [s], median (range) "
        "| the ego's speed then [m/s], median (range) "
        "| closing speed [m/s], median (range) | the vehicle ahead's hardest braking [m/s²], median (range) "
        "| it braked harder than the ego can | won by a lane chosen in hindsight | collisions no search avoids |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    for name, env_id in ENV_IDS.items():
        if args.env not in ("all", name):
            continue
        for density in densities:
            scripted = run(env_id, density, False, args.episodes, args.seed)
            braking = run(env_id, density, True, args.episodes, args.seed)
            collisions = braking["collisions"]
            searched = "— | —"  # the search changes lanes: multi-lane only
            if name == "multilane":
                won, won_cell = 0, "—"
                if collisions:
                    env = gym.make(env_id, density=density)
                    won = sum(evasion(env, r["seed"]) is not None for r in collisions)
                    env.close()
                    won_cell = f"{won} of {len(collisions)}"
                searched = f"{won_cell} | {(len(collisions) - won) / args.episodes:.0%}"
            print(
                f"| {name} | {density} | {scripted['arrival_rate']:.0%}, {scripted['collision_rate']:.0%} | "
                f"{braking['arrival_rate']:.0%}, {braking['collision_rate']:.0%} | {summary(collisions, braking['limit'])} | "
                f"{searched} |",
                flush=True,
            )
    seeds = f"seeds {args.seed}-{args.seed + args.episodes - 1}"
    machine = platform.processor() or platform.machine()
    print(f"\n{args.episodes} episodes per row and driver ({seeds}); {machine}, {time.time() - started:.0f} s\n`{command}`")


if __name__ == "__main__":
    main()
