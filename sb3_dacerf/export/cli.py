"""
Export a DACER-F, DACER or DSAC model saved with ``model.save()`` to ONNX or TorchScript.

    python -m sb3_dacerf.export MODEL.zip --format onnx --out policy.onnx
    python -m sb3_dacerf.export MODEL.zip --format torchscript --vec-normalize vecnormalize.json

It reads the model's weights and the statistics' JSON and runs no code from the files (see ``docs/guide/loading.md``).
"""

import argparse
import pickle
from pathlib import Path

from stable_baselines3.common.vec_env import VecNormalize

from sb3_dacerf.common.persistence import check_sha256, load_vec_normalize, saved_algorithm_name
from sb3_dacerf.dacer.dacer import DACER
from sb3_dacerf.dacer.policies import DiffusionActor
from sb3_dacerf.dacerf.dacerf import DACERF
from sb3_dacerf.dsac.dsac import DSAC
from sb3_dacerf.dsac.policies import GaussianActor
from sb3_dacerf.export.backends import EXPORT_FORMATS, export_policy

#: The algorithms the command exports, by the lower-case name a model zip records
ALGORITHMS: dict[str, type[DACERF] | type[DACER] | type[DSAC]] = {"dacerf": DACERF, "dacer": DACER, "dsac": DSAC}


def load_model(path: Path, unsafe_run_code_from_file: bool = False) -> DACERF | DACER | DSAC:
    """
    Load a DACERF, DACER or DSAC model on the CPU, the algorithm read from the file's JSON, running no code from the
    file (unless ``unsafe_run_code_from_file``, see :meth:`~sb3_dacerf.common.persistence.TwinCriticPersistence.load`).
    A file listed in a ``SHA256SUMS`` beside it must match its checksum.

    :raises ValueError: if the file holds another algorithm's model (naming it), or does not match its checksum
    """
    check_sha256(path)
    algorithm = saved_algorithm_name(path) or "dacerf"
    if algorithm not in ALGORITHMS:
        raise ValueError(f"{path} holds a {algorithm.upper()} model: the command exports DACERF, DACER and DSAC models")
    return ALGORITHMS[algorithm].load(path, device="cpu", unsafe_run_code_from_file=unsafe_run_code_from_file)


def load_statistics(path: Path, unsafe_run_code_from_file: bool = False) -> VecNormalize:
    """
    Observation statistics: the JSON of ``save_vec_normalize`` (checked against a ``SHA256SUMS`` beside it), or, only
    with ``unsafe_run_code_from_file``, a pickle written by ``VecNormalize.save``, which runs any code it holds.
    """
    check_sha256(path)
    if path.suffix != ".pkl":
        return load_vec_normalize(path)
    if not unsafe_run_code_from_file:
        raise ValueError(
            f"{path} is a pickle, which runs any code it holds when read. Convert your own statistics to JSON with "
            "sb3_dacerf.common.persistence.save_vec_normalize(VecNormalize.load(...), 'stats.json'), or, if you trust "
            "the file, pass --unsafe-run-code-from-file."
        )
    with open(path, "rb") as file:
        return pickle.load(file)  # what VecNormalize.load does, without an environment to wrap


def main() -> None:
    """The command line: ``python -m sb3_dacerf.export --help``."""
    parser = argparse.ArgumentParser(
        prog="python -m sb3_dacerf.export", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("model", type=Path, help="DACERF, DACER or DSAC model saved with model.save() (.zip)")
    parser.add_argument("--format", choices=EXPORT_FORMATS, default="onnx")
    parser.add_argument("--out", type=Path, help="output file (default: the model's name with .onnx or .pt)")
    parser.add_argument(
        "--n-sampling-steps",
        type=int,
        help="DACERF: Euler steps fixed in the graph (default: the model's); not for DACER or DSAC",
    )
    parser.add_argument(
        "--vec-normalize", type=Path, help="observation statistics (.json, written by save_vec_normalize) to bake into the graph"
    )
    parser.add_argument("--opset", type=int, default=17, help="ONNX opset version")
    parser.add_argument(
        "--unsafe-run-code-from-file",
        action="store_true",
        help="also read files that need unpickling (a model saved by another package, VecNormalize .pkl statistics): "
        "a crafted file runs any code it holds. Only for files you made or trust",
    )
    args = parser.parse_args()
    unsafe = args.unsafe_run_code_from_file

    if not args.model.is_file():
        parser.error(f"no model file at {args.model}")
    try:
        model = load_model(args.model, unsafe)
    except (OSError, ValueError, KeyError, RuntimeError) as error:
        parser.error(f"could not load {args.model} as a DACERF, DACER or DSAC model: {type(error).__name__}: {error}")
    vec_normalize = None
    if args.vec_normalize is not None:
        if not args.vec_normalize.is_file():
            parser.error(f"no VecNormalize statistics file at {args.vec_normalize}")
        try:
            vec_normalize = load_statistics(args.vec_normalize, unsafe)
        except (OSError, ValueError, pickle.UnpicklingError, EOFError, AttributeError, ImportError) as error:
            parser.error(f"could not read {args.vec_normalize} as observation statistics: {type(error).__name__}: {error}")
    out = args.out or args.model.with_suffix(".onnx" if args.format == "onnx" else ".pt")
    try:
        export_policy(model, out, args.format, args.n_sampling_steps, vec_normalize, args.opset)
    except (TypeError, ValueError, FileNotFoundError) as error:
        parser.error(str(error))
    if isinstance(model.actor, GaussianActor):
        steps = "one network call"
    elif isinstance(model.actor, DiffusionActor):
        steps = f"{model.actor.n_diffusion_steps} diffusion step(s)"
    else:
        steps = f"{model.actor.n_sampling_steps if args.n_sampling_steps is None else args.n_sampling_steps} Euler step(s)"
    print(f"Exported {args.model} ({args.format}, {steps}) to {out}")


__all__ = ["ALGORITHMS", "load_model", "load_statistics", "main"]
