"""
Export a driving run's checkpoint of ``benchmarks/learning_curves.py`` as a model that ``examples/evaluate_driving.py``
and ``examples/render_driving.py`` load (the format of the models in ``examples/models/``):

    python benchmarks/export_driver.py benchmarks/results/multilane/checkpoints/DACERF-Multilane-v0/dacerf-seed1 \\
        examples/models/dacerf_multilane_rl
    python examples/evaluate_driving.py examples/models/dacerf_multilane_rl --episodes 50
    python examples/render_driving.py --model examples/models/dacerf_multilane_rl

A checkpoint is the folder ``<out>/checkpoints/<env>/<variant>-seed<N>/`` (``model.zip``, ``env.pkl``,
``replay_buffer.npz``, ``state.pkl``). From it ``STEM`` gets:

- ``STEM.zip``: the model, loadable with its algorithm's ``load`` (``DACERF.load`` for the variants ``dacerf`` and
  ``dacerf-paper``, ``DACER.load``, ``DSAC.load``, ``SAC.load`` for ``dacer``, ``dsac``, ``sac``), without the replay
  buffer and, unless ``--keep-optimizer``, without the optimizers' moment estimates (their settings are kept, so the
  model loads and can train on, with Adam restarting from zero moments);
- ``STEM.json``: ``env_id``, ``density``, ``config`` and ``algo``, the metadata ``examples/train_driving.py --save``
  writes;
- ``STEM_vecnormalize.json``: the run's observation statistics (``save_vec_normalize``, ``training=False``), if the
  run normalised observations (``learning_curves.py --vec-normalize``).

When STEM's folder has a ``SHA256SUMS`` (``examples/models/``), the checksums of the written files are updated in it.

The environment id and its ``gym.make`` keyword arguments (``density``, ``config``, less the keys every evaluation
sets: ``evaluate_driving.evaluation_config``) are read from the environment pickled in the checkpoint (its ``spec``),
else from the folder's path; the algorithm from the policy class saved in
the model. ``--env``, ``--env-kwargs`` and ``--algo`` override them. The exported files are loaded back once with
``evaluate_driving.load_driver`` before the command ends, so an export that would not evaluate fails here.

``env.pkl`` is a pickle: export only checkpoints you made or trust.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path
from typing import Any

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent / "examples")]  # learning_curves.py and evaluate_driving.py
from evaluate_driving import (  # noqa: E402
    ALGORITHMS,
    SCENARIOS,
    algorithm_names,
    evaluation_config,
    load_algorithm,
    load_driver,
    model_paths,
    saved_algorithm,
)

CHECKPOINT_FILES = ("model.zip", "env.pkl")


def check_checkpoint(folder: Path) -> None:
    """Exit with a message naming the problem unless ``folder`` holds a learning_curves checkpoint."""
    usage = "pass a run's folder <out>/checkpoints/<env>/<variant>-seed<N> written by benchmarks/learning_curves.py"
    if not folder.is_dir():
        sys.exit(f"error: {str(folder)!r} is not a folder: {usage}")
    missing = [name for name in CHECKPOINT_FILES if not (folder / name).is_file()]
    if missing:
        runs = sorted(path.parent for pattern in ("*/env.pkl", "*/*/env.pkl") for path in folder.glob(pattern))
        hint = f"; checkpoints below it: {', '.join(str(run) for run in runs[:6])}" if runs else ""
        sys.exit(f"error: {str(folder)!r} is not a learning_curves checkpoint (no {' or '.join(missing)}): {usage}{hint}")


def path_names(folder: Path) -> tuple[str | None, str | None]:
    """The env id and the variant a checkpoint folder's path names (``<env>/<variant>-seed<N>``), or ``None``."""
    match = re.fullmatch(r"(.+)-seed\d+", folder.resolve().name)
    return folder.resolve().parent.name or None, match.group(1) if match else None


def variant_algorithm(variant: str | None) -> str | None:
    """The lower-case algorithm name of a learning_curves.py variant (``dacerf-paper``: ``dacerf``), else ``None``."""
    from learning_curves import VARIANTS

    return VARIANTS[variant][0].lower() if variant in VARIANTS else None


def file_size(path: str) -> str:
    size = os.path.getsize(path)
    return f"{size / 1e6:.2f} MB" if size >= 100_000 else f"{size / 1e3:.1f} kB"


def drop_optimizer_state(model: Any) -> None:
    """
    Empty the per-parameter state (Adam's moment estimates) of every optimizer ``model.save`` writes. Their
    hyper-parameters stay, and ``load`` restores an empty state, which Adam fills again at its next step.
    """
    import torch as th
    from stable_baselines3.common.save_util import recursive_getattr

    for name in model._get_torch_save_params()[0]:
        attribute = recursive_getattr(model, name)
        if isinstance(attribute, th.optim.Optimizer):
            attribute.state.clear()


def checkpoint_environment(
    folder: Path, saved: dict[str, Any], env_id: str | None, env_kwargs: dict | None
) -> tuple[str, dict[str, Any]]:
    """
    The environment id and ``gym.make`` keyword arguments to export for: those given, else those of the environment
    pickled in the checkpoint (its ``spec``), else the env id the folder's path names.
    """
    env = getattr(saved["venv"], "envs", [None])[0]
    spec = getattr(env, "spec", None)
    recorded_env = spec.id if spec is not None else path_names(folder)[0]
    env_id = env_id or recorded_env
    if env_id not in SCENARIOS.values():
        sys.exit(
            f"error: {folder} is a run of {env_id!r}, not a driving scenario ({', '.join(SCENARIOS.values())}): "
            "pass --env if the folder was moved"
        )
    if recorded_env and env_id != recorded_env:
        print(f"note: the checkpoint's environment is {recorded_env}; exporting for {env_id} as asked (--env)")
    if env_kwargs is None:
        env_kwargs = {k: v for k, v in (spec.kwargs if spec is not None else {}).items() if k != "render_mode"}
        config = env_kwargs.get("config") or {}
        evaluated = sorted(set(config) & set(evaluation_config(env_id)))
        if evaluated:
            env_kwargs["config"] = {k: v for k, v in config.items() if k not in evaluated}
            print(f"note: the config key(s) {evaluated} are left out of the exported metadata (evaluations set them)")
    unknown = set(env_kwargs) - {"density", "config"}
    if unknown:
        sys.exit(
            f"error: gym.make keyword arguments {sorted(unknown)} cannot be stored in the model's metadata "
            "(density and config only): pass --env-kwargs with those two"
        )
    return env_id, env_kwargs


def checkpoint_algorithm(folder: Path, algo: str | None) -> str:
    """The algorithm to load the checkpoint's model with: ``algo``, else the saved policy's, else the variant's."""
    saved_algo = saved_algorithm(folder / "model.zip")
    if algo and saved_algo and algo != saved_algo:
        sys.exit(f"error: {folder / 'model.zip'} holds a {saved_algo} model, not {algo}: leave out --algo")
    algo = algo or saved_algo or variant_algorithm(path_names(folder)[1])
    if algo is None:
        sys.exit(f"error: cannot tell the algorithm of {folder / 'model.zip'}: pass --algo ({algorithm_names()})")
    if algo not in ALGORITHMS:
        sys.exit(f"error: {folder} is a {algo} run: evaluate_driving.py loads {algorithm_names('and')} models only")
    return algo


def check_spaces(model: Any, normalize: Any, env_id: str, env_kwargs: dict[str, Any]) -> None:
    """Exit unless the model's (and the statistics') spaces are those of ``gym.make(env_id, **env_kwargs)``."""
    import gymnasium as gym

    try:
        env = gym.make(env_id, **env_kwargs)
    except (TypeError, ValueError) as error:
        sys.exit(f"error: gym.make({env_id!r}, **{env_kwargs}) fails ({error}): check --env-kwargs")
    shapes = {"observation": model.observation_space.shape, "action": model.action_space.shape}
    if normalize is not None:
        shapes["normalised observation"] = normalize.observation_space.shape
    for name, shape in shapes.items():
        expected = (env.action_space if name == "action" else env.observation_space).shape
        if shape != expected:
            sys.exit(
                f"error: the checkpoint's {name} shape is {shape}, {env_id} with {env_kwargs} has {expected}: "
                "export for the environment the run trained on (leave out --env / --env-kwargs)"
            )
    env.close()


def export(
    folder: Path,
    stem: str,
    env_id: str | None = None,
    env_kwargs: dict | None = None,
    algo: str | None = None,
    keep_optimizer: bool = False,
) -> dict[str, str]:
    """
    Write ``stem``.zip, .json and (with observation normalisation) _vecnormalize.json from a checkpoint, and their
    checksums into the ``SHA256SUMS`` of ``stem``'s folder if it has one.

    :param folder: the checkpoint folder
    :param stem: path of the exported files without suffix
    :param env_id: the environment id (default: the checkpoint's)
    :param env_kwargs: ``gym.make`` keyword arguments, ``density`` and ``config`` (default: the checkpoint's)
    :param algo: ``dacerf``, ``dacer``, ``dsac`` or ``sac`` (default: the saved policy's algorithm)
    :param keep_optimizer: keep the optimizers' moment estimates (about twice the file size)
    :return: the written paths, as ``evaluate_driving.model_paths``
    """
    import cloudpickle

    import sb3_dacerf  # noqa: F401  (registers the environment ids)
    from sb3_dacerf.common.persistence import CHECKSUMS, safe_save, save_vec_normalize, update_sha256sums

    check_checkpoint(folder)
    with open(folder / "env.pkl", "rb") as file:
        saved = cloudpickle.load(file)
    if not isinstance(saved, dict) or "venv" not in saved or "normalize" not in saved:
        sys.exit(f"error: {folder / 'env.pkl'} is not a learning_curves environment pickle (a dict with venv and normalize)")
    env_id, env_kwargs = checkpoint_environment(folder, saved, env_id, env_kwargs)
    algo = checkpoint_algorithm(folder, algo)
    algo_class = load_algorithm(algo)
    try:
        # The checkpoint is the user's own (env.pkl, a pickle, was read above): SB3's load for SAC, ours for the others
        model = algo_class.load(folder / "model.zip", device="cpu")
    except (OSError, ValueError, KeyError, RuntimeError) as error:  # a file of another class or a corrupt file
        sys.exit(f"error: cannot load {folder / 'model.zip'} as {algo_class.__name__} ({error}): check --algo")
    normalize = saved["normalize"]
    check_spaces(model, normalize, env_id, env_kwargs)  # before anything is written
    if not keep_optimizer:
        drop_optimizer_state(model)

    paths = model_paths(stem)
    os.makedirs(os.path.dirname(paths["model"]) or ".", exist_ok=True)
    safe_save(model, paths["model"])
    metadata = {
        "env_id": env_id,
        "density": env_kwargs.get("density", "normal"),
        "config": env_kwargs.get("config", {}),
        "algo": algo,
    }
    with open(paths["metadata"], "w") as file:
        json.dump(metadata, file)
    if normalize is not None:
        normalize.training = False
        save_vec_normalize(normalize, paths["vec_normalize"])
    elif os.path.isfile(paths["vec_normalize"]):
        os.remove(paths["vec_normalize"])  # left from an earlier export: evaluate_driving.py would use it
        print(f"removed {paths['vec_normalize']}: this run did not normalise observations")

    if os.path.isfile(os.path.join(os.path.dirname(paths["model"]) or ".", CHECKSUMS)):
        update_sha256sums([p for p in paths.values() if os.path.isfile(p)])
        print(f"updated {os.path.join(os.path.dirname(paths['model']), CHECKSUMS)}")
    # Load the files back as evaluate_driving.py does
    load_driver(paths["model"]).env.close()
    sizes = ", ".join(f"{os.path.basename(p)} {file_size(p)}" for p in paths.values() if os.path.isfile(p))
    print(
        f"{algo_class.__name__} at {model.num_timesteps} steps from {folder} -> {sizes}; {json.dumps(metadata)}"
        + ("" if normalize is not None else "; no observation normalisation")
    )
    return paths


def main(argv: list[str] | None = None) -> dict[str, str]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path, help="a run's folder <out>/checkpoints/<env>/<variant>-seed<N>")
    parser.add_argument("stem", help="path of the exported files without suffix, e.g. examples/models/dacerf_multilane_rl")
    parser.add_argument("--env", choices=list(SCENARIOS.values()), help="environment id (default: the checkpoint's)")
    parser.add_argument(
        "--env-kwargs",
        type=json.loads,
        help='gym.make keyword arguments as JSON, e.g. \'{"config": {"collision_penalty": 500}}\' (default: the checkpoint\'s)',
    )
    parser.add_argument("--algo", choices=list(ALGORITHMS), help="default: from the saved policy class")
    parser.add_argument("--keep-optimizer", action="store_true", help="keep the optimizers' moment estimates")
    args = parser.parse_args(argv)
    if args.env_kwargs is not None and not isinstance(args.env_kwargs, dict):
        parser.error(f"--env-kwargs must be a JSON object, got {args.env_kwargs!r}")
    return export(args.checkpoint, args.stem, args.env, args.env_kwargs, args.algo, args.keep_optimizer)


if __name__ == "__main__":
    main()
