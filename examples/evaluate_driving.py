"""
Evaluate a trained driver (DACERF, DACER, DSAC or SAC) on the paper's driving scenarios: total average return
(TAR), arrival, collision and off-road rates, mean episode length and the reward per term over N seeded episodes of
deterministic actions (``predict(deterministic=True)``: DACERF's flow from a zero start, DACER's reverse diffusion
from zero without posterior noise, DSAC's and SAC's ``tanh`` of the Gaussian's mean).

    python examples/evaluate_driving.py driving_multilane.zip --episodes 20
    python examples/evaluate_driving.py model.zip --env intersection --algo dsac --vec-normalize stats.json
    python examples/evaluate_driving.py --scripted --env multilane --episodes 50   # the scripted reference driver
    python examples/evaluate_driving.py --scripted junction --env intersection --episodes 50   # gap acceptance
    python examples/evaluate_driving.py --idle --env intersection --episodes 50    # zero increments: the floor
    python examples/evaluate_driving.py examples/models/dacerf_multilane_rl --density all --episodes 50   # one table

``--density all`` evaluates at each traffic density on the same seeds and prints one markdown table (TAR, arrival,
collision and off-road rates per density); ``--density`` also takes one density, ``random``, a comma-separated
list (``sparse,normal``) or a JSON dict of weights (``'{"sparse": 1, "dense": 3}'``) to draw one per episode.
``--zero-empty-rows`` gives the empty vehicle rows of the observation zeros after SB3's ``VecNormalize`` (the mean
of its statistics) instead of the values the statistics give them: a driver whose training saw every vehicle row
filled (trained in normal traffic with ``VecNormalize``) then drives in sparse traffic; drivers trained with
``sb3_dacerf.common.vec_normalize.MaskedVecNormalize`` need nothing of the kind.

A model saved by ``examples/train_driving.py --save NAME`` comes with ``NAME_<scenario>.json`` (env id, density,
config, algorithm) and, if it trained with ``--vec-normalize``, ``NAME_<scenario>_vecnormalize.json``: both are
found next to the model and used, so only the model path is needed. The files are read without running code from
them: the model's weights with ``torch.load(weights_only=True)``, the statistics and metadata as JSON, the env id
and the algorithm from closed lists; files listed in a ``SHA256SUMS`` beside them (the drivers of
``examples/models/``) must match their checksums. A model saved by another program than ``train_driving.py``,
``export_driver.py`` or this package's ``save`` (e.g. SB3's ``SAC.save``), or VecNormalize statistics pickled by
``VecNormalize.save`` (``--vec-normalize stats.pkl``), are read only with ``--unsafe-run-code-from-file``: a crafted
file then runs any code it holds. ``benchmarks/export_driver.py`` writes the
same three files from a ``benchmarks/learning_curves.py`` checkpoint (the format of ``examples/models/``), and
``examples/render_driving.py --model`` renders an episode of such a model, loaded by ``load_driver`` below.

Arrival is ``info["is_success"]``: the route's exit reached at the intersection, the time limit reached without
collision or leaving the road on the highway. Evaluation seeds default to 10,000 + i, which training resets never
use. Episodes start from the scenario's standard starts whatever the model trained on (``evaluation_config``: at the
intersection ``reference_start_probability`` 0, 20-40 m before the junction); ``--config`` can still set the key.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import load_env_creator
from stable_baselines3 import SAC
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

import sb3_dacerf  # noqa: F401  (registers the environment ids)
from sb3_dacerf import DACER, DACERF, DSAC
from sb3_dacerf.common.persistence import check_sha256, load_vec_normalize, safe_load, saved_algorithm_name
from sb3_dacerf.envs.driving import SCRIPTED_DRIVER_NAMES
from sb3_dacerf.envs.driving.density import DENSITIES, DensitySpec, density_weights

SCENARIOS = {"multilane": "DACERF-Multilane-v0", "intersection": "DACERF-Intersection-v0"}
#: The algorithms the driving examples train and load, by the name ``--algo`` takes and the metadata's ``algo`` holds
#: (``train_driving.py``, ``evaluate_driving.py``, ``render_driving.py``, ``benchmarks/export_driver.py``)
ALGORITHMS: dict[str, type[OffPolicyAlgorithm]] = {"dacerf": DACERF, "dacer": DACER, "dsac": DSAC, "sac": SAC}


def evaluation_config(env_id: str, trained: dict | None = None, config: dict | None = None) -> dict:
    """
    The config an evaluation of ``env_id`` runs under: the env class's ``EVALUATION_CONFIG`` (the intersection's
    standard starts), then ``trained`` (the config the model trained with) without its keys, then ``config`` (explicit
    overrides, which may set them: to evaluate from other starts on purpose). ``{}`` for an env without one.
    """
    entry_point = gym.spec(env_id).entry_point
    env_class = load_env_creator(entry_point) if isinstance(entry_point, str) else entry_point
    fixed = getattr(env_class, "EVALUATION_CONFIG", {})
    return {**fixed, **{k: v for k, v in (trained or {}).items() if k not in fixed}, **(config or {})}


def algorithm_names(conjunction: str = "or") -> str:
    """The names of :data:`ALGORITHMS` for a message: ``dacerf, dacer, dsac or sac``."""
    names = list(ALGORITHMS)
    return f"{', '.join(names[:-1])} {conjunction} {names[-1]}"


@dataclass
class Driver:
    """A saved driver loaded by ``load_driver``: the model, its environment and its observation normalisation."""

    model: Any
    env: gym.Env
    env_id: str
    density: DensitySpec
    config: dict
    vec_normalize: Any  # VecNormalize (training=False) or None
    stats_path: str | None
    path: str
    empty_rows: tuple[int, int, int] | None = None
    """With ``zero_empty_rows``: the vehicle rows (``vehicle_rows``) whose empty ones are given zeros."""

    def act(self, obs: np.ndarray) -> np.ndarray:
        """The deterministic action for a raw (not normalised) observation."""
        return deterministic_action(self.model, self.vec_normalize, obs, self.empty_rows)


def deterministic_action(model, vec_normalize, obs: np.ndarray, empty_rows: tuple[int, int, int] | None = None) -> np.ndarray:
    """
    A model's deterministic action for a raw observation, normalised first with ``vec_normalize`` if not None.

    :param empty_rows: ``(start, count, size)`` of a table of rows whose last entry is a mask: the normalised
        observation's rows with mask 0 in ``obs`` are set to zeros (see ``--zero-empty-rows``)
    """
    if vec_normalize is not None:
        normalized = vec_normalize.normalize_obs(obs)
        if empty_rows is not None:
            start, count, size = empty_rows
            empty = np.asarray(obs)[start : start + count * size].reshape(count, size)[:, -1] <= 0.5
            normalized[start : start + count * size].reshape(count, size)[empty] = 0.0
        obs = normalized
    return model.predict(obs, deterministic=True)[0]


def policy_act(model, vec_normalize=None, empty_rows: tuple[int, int, int] | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """
    The deterministic driving function of an SB3 model: raw observation in, action out.

    :param model: a trained SB3 model
    :param vec_normalize: the ``VecNormalize`` whose observation statistics the model was trained with, if any
    :param empty_rows: the rows whose empty ones get zeros after normalisation (``deterministic_action``)
    """
    return functools.partial(deterministic_action, model, vec_normalize, empty_rows=empty_rows)


def parse_density(text: str) -> DensitySpec:
    """
    A ``--density`` value: a density, ``random``, ``all`` (``evaluate_driving.py``: each in turn), a comma-separated
    list of densities or a JSON dict of weights, checked as ``gym.make`` checks it.

    :raises argparse.ArgumentTypeError: a value ``gym.make`` would refuse, with its message
    """
    if text == "all":
        return text
    density: DensitySpec = text
    if text.lstrip().startswith("{"):
        try:
            density = json.loads(text)
        except json.JSONDecodeError as error:
            raise argparse.ArgumentTypeError(f"{text!r} is not a JSON dict of weights ({error})") from None
    elif "," in text:
        density = [name.strip() for name in text.split(",")]
    try:
        density_weights(density)
    except (TypeError, ValueError) as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return density


def format_density_table(results: dict[str, dict[str, Any]]) -> str:
    """
    One markdown table of ``evaluate`` results by density.

    :param results: ``{density: evaluate(...)}``
    """
    lines = [
        "| density | TAR | arrival | collision | off road | mean length | distance to the reference path | speed error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for density, r in results.items():
        lines.append(
            f"| {density} | {r['tar']:,.0f} | {r['arrival_rate']:.0%} | {r['collision_rate']:.0%} | "
            f"{r['off_road_rate']:.0%} | {r['episode_length']:.0f} steps | {r['lateral_error']:.2f} m | "
            f"{r['speed_error']:.2f} m/s |"
        )
    return "\n".join(lines)


def model_paths(model_path: str) -> dict[str, str]:
    """The files that ``train_driving.py --save`` writes beside a model: metadata JSON and VecNormalize statistics."""
    stem = model_path[:-4] if model_path.endswith(".zip") else model_path
    return {"model": stem + ".zip", "metadata": stem + ".json", "vec_normalize": stem + "_vecnormalize.json"}


def evaluate(act: Callable[[np.ndarray], np.ndarray], env: gym.Env, n_episodes: int, seed: int) -> dict[str, Any]:
    """
    Run evaluation episodes.

    :param act: the driver: raw observation in, action out (``Driver.act``, ``policy_act(model)``, a
        :class:`~sb3_dacerf.envs.driving.scripted.ScriptedDriver`)
    :param env: the evaluation environment (not normalised)
    :param n_episodes: number of episodes
    :param seed: seed of the first episode, the next ones use the following seeds
    :return: TAR and its spread, arrival / collision / off-road rates, mean episode length, and the mean absolute
        distance to the reference path [m] and speed error [m/s] over all steps; ``by_outcome``: episodes, TAR and
        mean length of the episodes that ended each way (arrival, collision, off road, time limit); ``reward_terms``:
        each term of the reward (``info["reward_terms"]``) summed over an episode, mean over the episodes; at the
        intersection also ``by_route``: episodes and rates for each route drawn (straight, left, right, U-turn)
    """
    returns, outcomes, lengths, routes = [], [], [], []
    term_sums: dict[str, float] = {}
    lateral_errors, speed_errors = [], []  # per step, over all episodes
    for episode in range(n_episodes):
        obs, info = env.reset(seed=seed + episode)
        route = info.get("route")
        done, total, length = False, 0.0, 0
        while not done:
            obs, reward, terminated, truncated, info = env.step(act(obs))
            total, length, done = total + float(reward), length + 1, terminated or truncated
            lateral_errors.append(abs(info["lateral_error"]))
            speed_errors.append(abs(info["speed"] - info["reference_speed"]))
            for term, value in info["reward_terms"].items():
                term_sums[term] = term_sums.get(term, 0.0) + float(value)
        returns.append(total)
        outcomes.append((info["is_success"], info["collision"], info["off_road"]))
        lengths.append(length)
        routes.append(route)
    outcomes_array = np.asarray(outcomes, dtype=float)

    def rates(episodes: np.ndarray) -> dict[str, float]:
        arrival, collision, off_road = outcomes_array[episodes].mean(axis=0)
        return {"arrival_rate": float(arrival), "collision_rate": float(collision), "off_road_rate": float(off_road)}

    results: dict[str, Any] = {
        "tar": float(np.mean(returns)),
        "tar_std": float(np.std(returns)),
        **rates(np.ones(n_episodes, dtype=bool)),
        "episode_length": float(np.mean(lengths)),
        "lateral_error": float(np.mean(lateral_errors)),
        "speed_error": float(np.mean(speed_errors)),
        "reward_terms": {term: total / n_episodes for term, total in term_sums.items()},
    }
    # What each way of ending an episode scores: the TAR mixes how well the arriving episodes track their reference
    # with how often and how early the others end
    ends = np.array(["arrival" if a else "collision" if c else "off road" if o else "time limit" for a, c, o in outcomes])
    returns_array, lengths_array = np.asarray(returns), np.asarray(lengths)
    results["by_outcome"] = {
        end: {
            "episodes": int(episodes.sum()),
            "tar": float(returns_array[episodes].mean()),
            "episode_length": float(lengths_array[episodes].mean()),
        }
        for end in ("arrival", "collision", "off road", "time limit")
        if (episodes := ends == end).any()
    }
    if any(route is not None for route in routes):
        results["by_route"] = {}
        for route in sorted(set(routes), key=str):
            episodes = np.array([r == route for r in routes])
            results["by_route"][route] = {"episodes": int(episodes.sum()), **rates(episodes)}
    return results


def format_results(env_id: str, results: dict[str, Any], n_episodes: int) -> str:
    return (
        (
            f"{env_id}: over {n_episodes} episodes TAR {results['tar']:.1f} +/- {results['tar_std']:.1f}, "
            f"arrival rate {results['arrival_rate']:.0%}, collision rate {results['collision_rate']:.0%}, "
            f"off-road rate {results['off_road_rate']:.0%}, mean length {results['episode_length']:.0f} steps, "
            f"mean distance to the reference path {results['lateral_error']:.2f} m, "
            f"mean speed error {results['speed_error']:.2f} m/s"
        )
        + "\n  TAR by outcome: "
        + ", ".join(
            f"{end} {part['tar']:.0f} ({part['episodes']} episodes, {part['episode_length']:.0f} steps)"
            for end, part in results["by_outcome"].items()
        )
        + "\n  reward per episode by term: "
        + ", ".join(f"{term} {value:.1f}" for term, value in sorted(results["reward_terms"].items(), key=lambda item: item[1]))
        + "".join(
            f"\n  {route}: {rates['episodes']} episodes, arrival {rates['arrival_rate']:.0%}, "
            f"collision {rates['collision_rate']:.0%}, off-road {rates['off_road_rate']:.0%}"
            for route, rates in results.get("by_route", {}).items()
        )
    )


def load_algorithm(algo: str, source: str = "--algo") -> type[OffPolicyAlgorithm]:
    """
    The algorithm class of a name of :data:`ALGORITHMS`.

    :param algo: ``dacerf``, ``dacer``, ``dsac`` or ``sac``
    :param source: where the name comes from, for the error message (``--algo``, a metadata file, a saved policy)
    :return: the class, e.g. ``DSAC`` for ``dsac``
    """
    if algo not in ALGORITHMS:
        sys.exit(
            f"error: {algo!r} (from {source}) is not an algorithm the driving examples load: they load "
            f"{algorithm_names('and')} models (--algo {algorithm_names()})"
        )
    return ALGORITHMS[algo]


def saved_algorithm(model_path: str | os.PathLike) -> str | None:
    """
    The algorithm a model zip records, as a lower-case name (``dacerf``, ``dsac``, ``sac``, ``td3``...), read as
    JSON; ``None`` if it cannot be read.

    :param model_path: the model .zip
    """
    return saved_algorithm_name(model_path)


def checked(path: str) -> str:
    """``path``, after checking it against the ``SHA256SUMS`` beside it if that lists it; exits on a mismatch."""
    try:
        check_sha256(path)
    except ValueError as error:
        sys.exit(f"error: {error}")
    return path


def load_model(
    paths: dict[str, str], algo: str | None = None, metadata_algo: str | None = None, unsafe_run_code_from_file: bool = False
) -> OffPolicyAlgorithm:
    """
    Load a driver's model with the class of its algorithm: ``algo``, else the metadata's, else the one the model
    records (DACERF if it records none). Exits with a message naming the problem if the file holds another
    algorithm's model or cannot be loaded.

    :param paths: the driver's files, as ``model_paths`` gives them
    :param algo: a name of :data:`ALGORITHMS` (``--algo``)
    :param metadata_algo: the metadata's ``algo``
    :param unsafe_run_code_from_file: load with SB3's ``load``, which unpickles the file (needed for a model saved
        without ``sb3_dacerf.json``, e.g. by SB3's ``SAC.save``): a crafted file runs any code it holds
    """
    if algo is not None:
        algo_class = load_algorithm(algo)
    elif metadata_algo is not None:
        algo_class = load_algorithm(metadata_algo, repr(paths["metadata"]))
    else:
        saved = saved_algorithm(paths["model"])
        algo_class = load_algorithm(saved, f"the policy saved in {paths['model']!r}") if saved else DACERF
    checked(paths["model"])
    try:
        model = safe_load(algo_class, paths["model"], device="cpu", unsafe_run_code_from_file=unsafe_run_code_from_file)
    except (OSError, ValueError, KeyError, RuntimeError) as error:  # another algorithm's, a corrupt or unsafe file
        sys.exit(f"error: cannot load {paths['model']!r} as {algo_class.__name__} ({error}): check --algo ({algorithm_names()})")
    return model


def load_statistics(
    paths: dict[str, str],
    vec_normalize: str | None,
    env: gym.Env,
    env_id: str,
    density: DensitySpec,
    config: dict,
    unsafe_run_code_from_file: bool = False,
) -> tuple[str | None, Any]:
    """
    The path and the ``VecNormalize`` (``training=False``) of a driver's observation statistics: ``vec_normalize``,
    else the ``_vecnormalize.json`` beside the model; ``(None, None)`` without statistics. A ``.pkl`` is read only
    with ``unsafe_run_code_from_file``, never because it lies beside the model. Exits with a message on any problem.
    """
    normalizer = None
    stats = vec_normalize or (paths["vec_normalize"] if os.path.isfile(paths["vec_normalize"]) else None)
    if vec_normalize and not os.path.isfile(vec_normalize):
        sys.exit(f"error: no statistics file {vec_normalize!r}: pass the _vecnormalize.json saved with the model")
    pickled = paths["vec_normalize"][: -len(".json")] + ".pkl"
    if stats is None and os.path.isfile(pickled):
        sys.exit(
            f"error: {pickled!r} beside the model is a pickle, which is not read unless asked for (a crafted one runs "
            f"any code it holds). If you trust it, pass --vec-normalize {pickled} --unsafe-run-code-from-file"
        )
    if stats:
        from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

        venv = DummyVecEnv([lambda: gym.make(env_id, density=density, config=config)])
        if stats.endswith(".pkl") and not unsafe_run_code_from_file:
            sys.exit(
                f"error: {stats!r} is a pickle, which runs any code it holds when read: pass the statistics as JSON "
                "(sb3_dacerf.common.persistence.save_vec_normalize), or, if you trust the file, add --unsafe-run-code-from-file"
            )
        try:
            checked(stats)
            normalizer = VecNormalize.load(stats, venv) if stats.endswith(".pkl") else load_vec_normalize(stats, venv)
        except (ValueError, AssertionError) as error:  # not statistics, or of observations of another shape
            sys.exit(f"error: cannot use {stats!r} as the model's observation statistics: {error}")
        normalizer.training = False
        if normalizer.observation_space.shape != env.observation_space.shape:
            sys.exit(f"error: the statistics in {stats!r} are for observations of another shape: pass the model's own statistics")
    return stats, normalizer


def load_driver(
    model_path: str,
    scenario: str | None = None,
    algo: str | None = None,
    vec_normalize: str | None = None,
    density: str | None = None,
    config: dict | None = None,
    force: bool = False,
    render_mode: str | None = None,
    zero_empty_rows: bool | None = None,
    unsafe_run_code_from_file: bool = False,
) -> Driver:
    """
    Load a saved driver with what was saved beside it (see ``model_paths``), and make its environment.

    Settings left at ``None`` come from the metadata JSON: the scenario, the algorithm (else the saved policy's), the
    density (else ``normal``) and the config, merged by ``evaluation_config`` (the evaluation's keys over it, then
    ``config``'s single keys). The statistics beside the model (``_vecnormalize.json``) are used unless
    ``vec_normalize`` names another file. Every problem (missing file, another scenario than the model's, a file of
    another class, spaces that do not match, a checksum that does not match, a file that needs unpickling) exits with a
    message naming it.

    :param model_path: the model .zip (the suffix may be left out)
    :param scenario: ``multilane``, ``intersection`` or an env id
    :param algo: ``dacerf``, ``dacer``, ``dsac`` or ``sac`` (:data:`ALGORITHMS`)
    :param vec_normalize: path of statistics saved with ``sb3_dacerf.common.persistence.save_vec_normalize``
        (``.json``), or, with ``unsafe_run_code_from_file``, with ``VecNormalize.save`` (``.pkl``)
    :param density: ``sparse``, ``normal``, ``dense``, or a distribution to draw one per episode (``random``, a list,
        a dict of weights)
    :param config: env config overrides (of the metadata's and of the evaluation's)
    :param force: allow another scenario than the one the model was trained on
    :param render_mode: of the environment, e.g. ``"rgb_array"``
    :param zero_empty_rows: give the empty vehicle rows zeros after normalisation (``--zero-empty-rows``); default:
        the metadata's ``zero_empty_rows``, else ``False``
    :param unsafe_run_code_from_file: also read files that need unpickling (a model saved by SB3's ``save``, ``.pkl``
        statistics): a crafted file runs any code it holds
    """
    paths = model_paths(model_path)
    if not os.path.isfile(paths["model"]):
        sys.exit(
            f"error: no model file {paths['model']!r}: pass the .zip written by train_driving.py --save, "
            "benchmarks/export_driver.py or model.save()"
        )
    metadata: dict[str, Any] = {}
    if os.path.isfile(paths["metadata"]):
        try:
            with open(checked(paths["metadata"])) as file:
                metadata = json.load(file)
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            sys.exit(f"error: {paths['metadata']!r} is not JSON ({error}): pass the metadata written with the model")
        if not isinstance(metadata, dict):
            sys.exit(f"error: {paths['metadata']!r} holds a {type(metadata).__name__}, not the metadata's JSON object")
    trained_env = metadata.get("env_id")
    if trained_env is not None and trained_env not in SCENARIOS.values():
        sys.exit(
            f"error: {paths['metadata']!r} names the environment {trained_env!r}, none of {list(SCENARIOS.values())}: "
            "the driving examples make only these (an env id is never imported from a file)"
        )
    env_id = SCENARIOS.get(scenario, scenario) if scenario else trained_env
    if env_id is not None and env_id not in SCENARIOS.values():
        sys.exit(f"error: unknown scenario {scenario!r}: pass one of {list(SCENARIOS)} or {list(SCENARIOS.values())}")
    if env_id is None:
        sys.exit(
            f"error: {paths['metadata']!r} not found, so the scenario is unknown: pass --env multilane or --env intersection"
        )
    if trained_env and env_id != trained_env and not force:
        sys.exit(
            f"error: the model was trained on {trained_env} (per {paths['metadata']}), not {env_id}: "
            f"leave out --env, or add --force to evaluate it on another scenario"
        )
    density = density or metadata.get("density", "normal")
    config = evaluation_config(env_id, metadata.get("config", {}), config)
    env = gym.make(env_id, density=density, config=config, render_mode=render_mode)

    model = load_model(paths, algo, metadata.get("algo"), unsafe_run_code_from_file)
    for name in ("observation_space", "action_space"):
        if getattr(model, name).shape != getattr(env, name).shape:
            sys.exit(
                f"error: the model's {name} has shape {getattr(model, name).shape}, {env_id} with this config has "
                f"{getattr(env, name).shape}: evaluate on the scenario and config the model was trained with"
            )

    stats, normalizer = load_statistics(paths, vec_normalize, env, env_id, density, config, unsafe_run_code_from_file)
    if zero_empty_rows is None:
        zero_empty_rows = bool(metadata.get("zero_empty_rows", False))
    empty_rows = None
    if zero_empty_rows:
        if normalizer is None:
            sys.exit(f"error: --zero-empty-rows changes normalised observations, and {paths['model']!r} has no statistics")
        from sb3_dacerf.envs.driving.common.observation import vehicle_rows

        empty_rows = vehicle_rows(env.unwrapped.config)
    return Driver(model, env, env_id, density, config, normalizer, stats, paths["model"], empty_rows)


def baseline_driver(kind: str, env: gym.Env) -> Callable[[np.ndarray], np.ndarray]:
    """A scripted driver (``scripted``, ``junction``) or zero increments (``idle``) of one env."""
    if kind == "idle":
        return lambda obs: np.zeros(2, dtype=np.float32)
    from sb3_dacerf.envs.driving.scripted import SCRIPTED_DRIVERS

    return SCRIPTED_DRIVERS[kind](env)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", nargs="?", help="the model .zip (the .zip suffix may be left out)")
    parser.add_argument(
        "--scripted",
        nargs="?",
        const="scripted",
        choices=SCRIPTED_DRIVER_NAMES,
        help="evaluate a scripted driver instead of a model (needs --env): the reference driver, or 'junction', the "
        "intersection's gap-accepting driver",
    )
    parser.add_argument(
        "--idle",
        action="store_true",
        help="evaluate zero increments (the start speed and steering held) "
        "instead of a model (needs --env): the floor a trained driver must beat",
    )
    parser.add_argument("--env", choices=list(SCENARIOS), help="scenario (default: the one the model was trained on)")
    parser.add_argument(
        "--algo", choices=list(ALGORITHMS), help="model class (default: from the metadata, else the saved policy's)"
    )
    parser.add_argument(
        "--vec-normalize", help="observation statistics .json (default: the _vecnormalize.json saved beside the model)"
    )
    parser.add_argument(
        "--unsafe-run-code-from-file",
        action="store_true",
        help="also read files that need unpickling (a model saved by SB3's save, VecNormalize .pkl statistics): a crafted "
        "file runs any code it holds; only for files you made or trust",
    )
    parser.add_argument(
        "--density",
        type=parse_density,
        help="traffic density (default: as trained): sparse, normal, dense, 'all' (each in turn on the same seeds, one "
        "table), or one drawn per episode: random, a list 'sparse,normal' or a JSON dict of weights",
    )
    parser.add_argument(
        "--zero-empty-rows",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="give the empty vehicle rows zeros after normalisation (for drivers whose training saw every row filled; "
        "default: the metadata's zero_empty_rows; --no-zero-empty-rows turns it off)",
    )
    parser.add_argument("--config", type=json.loads, help="env config overrides as JSON, e.g. '{\"duration\": 20}'")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=10_000, help="seed of the first episode")
    parser.add_argument("--force", action="store_true", help="evaluate on another scenario than the model was trained on")
    args = parser.parse_args(argv)

    if args.scripted and args.idle:
        parser.error("--scripted and --idle are two baselines: pass one of them")
    densities = DENSITIES if args.density == "all" else (args.density,)
    seeds = f"seeds {args.seed}-{args.seed + args.episodes - 1}"
    if args.scripted or args.idle:
        name = "--scripted" if args.scripted else "--idle"
        if args.model or not args.env:
            parser.error(f"{name} evaluates a baseline driver: pass --env multilane or --env intersection and no model")
        if args.zero_empty_rows:
            parser.error("--zero-empty-rows changes a model's normalised observations: leave it out with --scripted / --idle")
        if args.scripted == "junction" and args.env != "intersection":
            parser.error("--scripted junction drives the intersection: pass --env intersection (or plain --scripted)")
        env_id, kind = SCENARIOS[args.env], args.scripted or "idle"
        label = "Zero increments" if kind == "idle" else {"scripted": "ScriptedDriver", "junction": "JunctionDriver"}[kind]
        by_density = {}
        for density in densities:
            density = density or "normal"
            env = gym.make(env_id, density=density, config=evaluation_config(env_id, config=args.config))
            print(f"{label}; {env_id} ({density}), {seeds}")
            results = evaluate(baseline_driver(kind, env), env, args.episodes, args.seed)
            if args.density != "all":
                print(format_results(env_id, results, args.episodes))
                return results
            by_density[density] = results
        print(format_density_table(by_density))
        return by_density
    if not args.model:
        parser.error("pass a model .zip to evaluate (or --scripted / --idle --env SCENARIO for a baseline driver)")
    by_density = {}
    for density in densities:
        driver = load_driver(
            args.model,
            args.env,
            args.algo,
            args.vec_normalize,
            density,
            args.config,
            args.force,
            None,
            args.zero_empty_rows,
            args.unsafe_run_code_from_file,
        )
        print(
            f"{type(driver.model).__name__} from {driver.path}"
            + (f", observations normalised with {driver.stats_path}" if driver.stats_path else "")
            + (", empty vehicle rows zeroed" if driver.empty_rows else "")
            + f"; {driver.env_id} ({driver.density}), {seeds}, deterministic actions"
        )
        results = evaluate(driver.act, driver.env, args.episodes, args.seed)
        if args.density != "all":
            print(format_results(driver.env_id, results, args.episodes))
            return results
        by_density[str(density)] = results
    print(format_density_table(by_density))
    return by_density


if __name__ == "__main__":
    main()
