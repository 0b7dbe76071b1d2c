"""
Environment steps per second of the driving scenarios, beside highway-env's own environments.

For each scenario, in one process, interleaved in rounds and, within a round, taking turns every 10 steps (so that
machine load hits all alike; the overhead is also given as the median and range of the per-round ratios), with the
same constant action (zero acceleration / increments, zero steering) at the same policy frequency (10 Hz),
timing ``env.step`` only (resets are not timed), in CPU time of the process by default (``--clock wall`` for wall-clock):

- ``highway-env default``: highway-env's ``highway-v0`` / ``intersection-v0`` with ``ContinuousAction`` and
  ``policy_frequency`` 10, otherwise its defaults (50 vehicles at 15 Hz physics on the highway). This shows
  the absolute speed a user gets from the stock environment; its traffic differs from ours, so it does
  not measure our overhead.
- ``same traffic, highway-env layer``: our environment class (same road, traffic, vehicle counts, 10 Hz
  physics, vehicle recycling), with highway-env's own ``Kinematics`` observation, ``ContinuousAction`` and
  reward / termination (``offroad_terminal`` on) / info instead of ours: what the same traffic costs under
  highway-env's task layer (its pandas-based observation is slower than ours).
- ``same traffic, no layer``: the same traffic with a constant observation, zero reward and our termination
  (collision or centre off the road). The zero action drives the ego exactly as ours does (zero
  acceleration and steering), so with the same seeds its episodes are step for step ours: this is the
  bare simulation, and ``overhead = t_step(ours) / t_step(no layer) - 1`` is the full cost of our
  observation / action / reward / info layer.
- ``ours, highway-env's simulation classes``: our environment with ``fast_simulation=False``: highway-env's own
  ``Road`` / ``RegulatedRoad``, ``RoadNetwork`` and ``IDMVehicle`` instead of the faster classes of
  ``sb3_dacerf.envs.driving.common.simulation``, which give the same traffic (the same episodes for the same seeds):
  ``speed-up = t_step(that) / t_step(ours)``.

``--profile`` prints instead where the steps spend their time (cProfile, both simulations, the functions that
dominate highway-env's). ``--scripted`` checks instead that the two simulations drive the same episodes: the scripted drivers
(``ScriptedDriver`` on both scenarios, ``JunctionDriver`` at the intersection) on 50 unseen seeds (10,000-10,049), each
with both simulations, printing the arrival and collision rates and how many episodes differ in any observation,
reward or flag.

Usage::

    python benchmarks/driving_env_speed.py [--steps 100] [--rounds 15] [--density normal] [--quick]
    python benchmarks/driving_env_speed.py --scripted [--density normal] [--seeds 50]
    python benchmarks/driving_env_speed.py --profile --steps 600 [--density normal]

On a shared machine the load average (printed) moves all numbers; the ratios, measured interleaved, move less.
"""

from __future__ import annotations

import argparse
import os
import time

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import gymnasium as gym
import highway_env  # noqa: F401  (registers highway-v0 / intersection-v0)
import numpy as np
import torch
from highway_env.envs.common.abstract import AbstractEnv

from sb3_dacerf.envs.driving.intersection import IntersectionEnv
from sb3_dacerf.envs.driving.multilane import MultilaneEnv


class StockLayer:
    """
    highway-env's own task layer over one of our scenarios: our road, traffic and vehicle recycling under
    highway-env's step loop, ``Kinematics`` observation, ``ContinuousAction``, reward, termination
    (``offroad_terminal`` on) and info. Each scenario of ours derives from a highway-env environment (``HighwayEnv``,
    ``IntersectionEnv``); that class's methods are the ones used. Combine with a scenario by :func:`with_layer`.
    """

    @classmethod
    def stock_class(cls) -> type[AbstractEnv]:
        """The highway-env environment our scenario derives from: the first highway-env class in the MRO."""
        return next(base for base in cls.__mro__ if base.__module__.startswith("highway_env.") and base is not AbstractEnv)

    @classmethod
    def default_config(cls) -> dict:
        stock = cls.stock_class().default_config()
        return {**stock, **super().default_config(), "action": {"type": "ContinuousAction"}, "offroad_terminal": True}

    def define_spaces(self) -> None:
        AbstractEnv.define_spaces(self)

    def _reset(self) -> None:
        # Our scenario's road and vehicles (through highway-env's _reset), without our perception of the scene.
        self.stock_class()._reset(self)
        self.vehicle.MIN_SPEED = 0.0

    def step(self, action: np.ndarray) -> tuple:
        # The intersection's step is highway-env's step, then its traffic update (clear, spawn), as ours does
        return self.stock_class().step(self, action)

    def _reward(self, action: np.ndarray) -> float:
        return self.stock_class()._reward(self, action)

    def _rewards(self, action: np.ndarray) -> dict:
        return self.stock_class()._rewards(self, action)

    def _is_terminated(self) -> bool:
        return self.stock_class()._is_terminated(self)

    def _info(self, obs: np.ndarray, action: np.ndarray | None = None) -> dict:
        return self.stock_class()._info(self, obs, action)


class NoLayer(StockLayer):
    """A constant observation and zero reward: the bare simulation of the traffic."""

    def define_spaces(self) -> None:
        super().define_spaces()
        self.observation_type.observe = lambda: np.zeros(1, dtype=np.float32)

    def _reward(self, action: np.ndarray) -> float:
        return 0.0

    def _info(self, obs: np.ndarray, action: np.ndarray | None = None) -> dict:
        return {}

    def _is_terminated(self) -> bool:
        # Our termination, so that episodes (and so the simulated traffic) are the same as ours
        off_road = self._road_clearance(self.vehicle.position) < 0
        exited = self._has_exited() if hasattr(self, "_has_exited") else False  # the intersection's exits
        return bool(self.vehicle.crashed or off_road or exited)


def with_layer(layer: type[StockLayer], scenario: type[AbstractEnv]) -> type[AbstractEnv]:
    """``scenario`` (``MultilaneEnv`` or ``IntersectionEnv``) under ``layer`` (:class:`StockLayer` or :class:`NoLayer`)."""
    return type(f"{layer.__name__}{scenario.__name__}", (layer, scenario), {})


def time_steps(env: gym.Env, steps: int, seed: int, clock=time.process_time) -> float:
    """
    :param env: the environment, reset before the first call
    :param steps: number of steps to time
    :param seed: seed of the resets after episode ends
    :param clock: ``time.process_time`` (CPU time of this process) or ``time.perf_counter`` (wall-clock)
    :return: seconds spent in ``env.step``
    """
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    elapsed = 0.0
    for i in range(steps):
        start = clock()
        _, _, terminated, truncated, _ = env.step(action)
        elapsed += clock() - start
        if terminated or truncated:
            env.reset(seed=seed + i)
    return elapsed


def scripted_episodes(env: gym.Env, driver_class: type, seeds: range) -> tuple[list[tuple[bool, bool]], list[list]]:
    """
    :param env: a driving environment
    :param driver_class: ``ScriptedDriver`` or ``JunctionDriver``
    :param seeds: the reset seed of each episode
    :return: each episode's (arrived, collided), and its trace (observations, rewards and flags of every step)
    """
    outcomes, traces = [], []
    driver = driver_class(env)
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        trace: list = [obs]
        terminated = truncated = False
        info: dict = {}
        while not (terminated or truncated):
            obs, reward, terminated, truncated, info = env.step(driver(obs))
            trace.append((obs, reward, terminated, truncated))
        outcomes.append((bool(info["is_success"]), bool(info["crashed"])))
        traces.append(trace)
    return outcomes, traces


def same_trace(a: list, b: list) -> bool:
    """Whether two episode traces (see :func:`scripted_episodes`) are equal step for step."""
    return len(a) == len(b) and all(
        all(np.array_equal(x, y) for x, y in zip(step_a, step_b, strict=True))
        if isinstance(step_a, tuple)
        else np.array_equal(step_a, step_b)
        for step_a, step_b in zip(a, b, strict=True)
    )


def check_scripted(density: str, n_seeds: int) -> None:
    """Print the scripted drivers' arrival / collision rates with both simulations on seeds 10,000 onwards."""
    from sb3_dacerf.envs.driving.scripted import JunctionDriver, ScriptedDriver

    seeds = range(10_000, 10_000 + n_seeds)
    print(f"density={density}, seeds {seeds.start}-{seeds.stop - 1}\n")
    print("| scenario | driver | simulation | arrival | collision | episodes that differ |")
    print("|---|---|---|---|---|---|")
    for scenario, env_class, drivers in (
        ("multilane", MultilaneEnv, (ScriptedDriver,)),
        ("intersection", IntersectionEnv, (ScriptedDriver, JunctionDriver)),
    ):
        for driver_class in drivers:
            results = {
                fast: scripted_episodes(env_class(density=density, config={"fast_simulation": fast}), driver_class, seeds)
                for fast in (False, True)
            }
            differ = sum(not same_trace(a, b) for a, b in zip(results[False][1], results[True][1], strict=True))
            for fast, (outcomes, _) in results.items():
                arrival, collision = np.mean(outcomes, axis=0)
                name = "fast (default)" if fast else "highway-env's classes"
                cells = [scenario, driver_class.__name__, name, f"{arrival:.0%}", f"{collision:.0%}", f"{differ} of {len(seeds)}"]
                print(f"| {' | '.join(cells)} |")


PROFILED = {
    "Road.act (traffic decisions: IDM, MOBIL)": ("act", ("road.py", "simulation.py")),
    "Road.neighbour_vehicles": ("neighbour_vehicles", ("road.py", "simulation.py")),
    "Road.step (moves, collisions)": ("step", ("road.py", "regulation.py", "simulation.py")),
    "RegulatedRoad.enforce_road_rules": ("enforce_road_rules", ("regulation.py", "simulation.py")),
    "copy.deepcopy": ("deepcopy", ("copy.py",)),
    "RoadNetwork.get_closest_lane_index": ("get_closest_lane_index", ("road.py", "simulation.py")),
    "np.clip": ("clip", ("fromnumeric.py",)),
    "observe_scene (our observation)": ("observe_scene", ("observation.py",)),
}
"""Rows of the profile table: (function name, files it may be defined in); overrides and the functions they call
share a name, so the largest cumulative time among the matches is the one shown."""


def profile(steps: int, density: str) -> None:
    """Print where ``steps`` steps of each scenario spend their time under cProfile, with both simulations."""
    import cProfile
    import pstats

    print(f"density={density}, {steps} steps per scenario and simulation, zero action, cProfile (cumulative CPU seconds)\n")
    columns, tables = [], {}
    for scenario, env_class in (("multilane", MultilaneEnv), ("intersection", IntersectionEnv)):
        for fast in (False, True):
            env = env_class(density=density, config={"fast_simulation": fast})
            env.reset(seed=0)
            profiler = cProfile.Profile(time.process_time)  # CPU time: other processes move it far less
            profiler.enable()
            time_steps(env, steps, seed=0)
            profiler.disable()
            stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
            simulation = "fast" if fast else "highway-env's classes"
            column = f"{scenario}, {simulation}"
            columns.append(column)
            env_step = [
                cumulative
                for (path, _, name), (_, _, _, cumulative, _) in stats.items()
                if name == "step" and path.endswith(("abstract.py", "intersection.py"))
            ]
            tables[column] = {"env.step": max(env_step)}
            for row, (function, files) in PROFILED.items():
                times = [
                    cumulative
                    for (path, _, name), (_, _, _, cumulative, _) in stats.items()
                    if name == function and path.endswith(files)
                ]
                tables[column][row] = max(times, default=0.0)
    print(f"| function | {' | '.join(columns)} |")
    print(f"|---|{'---|' * len(columns)}")
    for row in ["env.step", *PROFILED]:
        print(f"| {row} | {' | '.join(f'{tables[column][row]:.2f}' for column in columns)} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=100, help="steps per environment and round")
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--density", default="normal", choices=["sparse", "normal", "dense"])
    parser.add_argument(
        "--clock",
        default="cpu",
        choices=["cpu", "wall"],
        help="cpu: this process's CPU time (time.process_time), which other processes on a shared machine move far less "
        "than wall-clock time; wall: time.perf_counter",
    )
    parser.add_argument("--quick", action="store_true", help="a short check: 50 steps x 4 rounds")
    parser.add_argument("--scripted", action="store_true", help="compare the scripted drivers' episodes on both simulations")
    parser.add_argument("--seeds", type=int, default=50, help="with --scripted: episodes per driver and simulation")
    parser.add_argument("--profile", action="store_true", help="profile --steps steps (600 or more) of each scenario")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.profile:
        profile(args.steps, args.density)
        return
    if args.scripted:
        check_scripted(args.density, 5 if args.quick else args.seeds)
        return
    if args.quick:
        args.steps, args.rounds = 50, 4

    stock_config = {"action": {"type": "ContinuousAction"}, "policy_frequency": 10}
    scenarios = {
        "multilane": {
            "highway-env default (highway-v0)": lambda: gym.make("highway-v0", config=stock_config),
            "same traffic, highway-env layer": lambda: with_layer(StockLayer, MultilaneEnv)(density=args.density),
            "same traffic, no layer": lambda: with_layer(NoLayer, MultilaneEnv)(density=args.density),
            "ours (DACERF-Multilane-v0)": lambda: MultilaneEnv(density=args.density),
            "ours, highway-env's simulation classes": lambda: MultilaneEnv(
                density=args.density, config={"fast_simulation": False}
            ),
        },
        "intersection": {
            "highway-env default (intersection-v0)": lambda: gym.make("intersection-v0", config=stock_config),
            "same traffic, highway-env layer": lambda: with_layer(StockLayer, IntersectionEnv)(density=args.density),
            "same traffic, no layer": lambda: with_layer(NoLayer, IntersectionEnv)(density=args.density),
            "ours (DACERF-Intersection-v0)": lambda: IntersectionEnv(density=args.density),
            "ours, highway-env's simulation classes": lambda: IntersectionEnv(
                density=args.density, config={"fast_simulation": False}
            ),
        },
    }
    clock = time.process_time if args.clock == "cpu" else time.perf_counter
    envs = {(scenario, name): make() for scenario, makers in scenarios.items() for name, make in makers.items()}
    for env in envs.values():
        env.reset(seed=0)
    # Within a round, the environments take turns every `chunk` steps, so that load changes hit them alike.
    per_round = {key: np.zeros(args.rounds) for key in envs}
    chunk = min(10, args.steps)
    for round_ in range(args.rounds):
        for first in range(0, args.steps, chunk):
            for key, env in envs.items():
                per_round[key][round_] += time_steps(env, chunk, seed=1000 * round_ + first, clock=clock)
    elapsed = {key: float(times.sum()) for key, times in per_round.items()}

    total_steps = args.steps * args.rounds
    print(
        f"density={args.density}, {total_steps} steps per environment, {args.rounds} interleaved rounds, policy 10 Hz, "
        f"{'CPU' if args.clock == 'cpu' else 'wall-clock'} time, "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"
    )
    for scenario, makers in scenarios.items():
        print(f"\n{scenario}")
        for name in makers:
            print(f"  {name:40s} {total_steps / elapsed[scenario, name]:8.1f} steps/s")
        names = list(makers)
        ours, stock_layer, bare = elapsed[scenario, names[3]], elapsed[scenario, names[1]], elapsed[scenario, names[2]]
        print(
            f"  our layer's overhead over the bare simulation: {ours / bare - 1:+.1%}, "
            f"{(ours - bare) / total_steps * 1e3:.2f} ms per step"
        )
        ratios = per_round[scenario, names[3]] / per_round[scenario, names[2]] - 1
        print(f"    per round: median {np.median(ratios):+.1%}, range [{ratios.min():+.1%}, {ratios.max():+.1%}]")
        print(f"  ours vs the same traffic under highway-env's layer: {ours / stock_layer - 1:+.1%}")
        stock_simulation = elapsed[scenario, names[4]]
        speedups = per_round[scenario, names[4]] / per_round[scenario, names[3]]
        print(f"  speed-up of the fast simulation (ours vs highway-env's classes): {stock_simulation / ours:.2f}x")
        print(f"    per round: median {np.median(speedups):.2f}x, range [{speedups.min():.2f}x, {speedups.max():.2f}x]")


if __name__ == "__main__":
    main()
