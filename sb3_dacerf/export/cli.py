"""
Export a DACER-F, DACER or DSAC model saved with ``model.save()`` to ONNX or TorchScript.

    python -m sb3_dacerf.export MODEL.zip --format onnx --out policy.onnx
    python -m sb3_dacerf.export MODEL.zip --format torchscript --vec-normalize vecnormalize.pkl
"""

import argparse
import pickle
from pathlib import Path

from sb3_dacerf.common.persistence import saved_policy_class
from sb3_dacerf.dacer.dacer import DACER
from sb3_dacerf.dacer.policies import DACERPolicy, DiffusionActor
from sb3_dacerf.dacerf.dacerf import DACERF
from sb3_dacerf.dsac.dsac import DSAC
from sb3_dacerf.dsac.policies import DSACPolicy, GaussianActor
from sb3_dacerf.export.backends import EXPORT_FORMATS, export_policy


def load_model(path: Path) -> DACERF | DACER | DSAC:
    """
    Load a DACERF, DACER or DSAC model on the CPU, the algorithm read from the file.

    :raises ValueError: if the file holds another algorithm's model, naming it
    """
    policy_class = saved_policy_class(path)
    if isinstance(policy_class, type) and issubclass(policy_class, DSACPolicy):
        return DSAC.load(path, device="cpu")
    algorithm = DACER if isinstance(policy_class, type) and issubclass(policy_class, DACERPolicy) else DACERF
    return algorithm.load(path, device="cpu")


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
    parser.add_argument("--vec-normalize", type=Path, help="VecNormalize statistics (.pkl) to bake into the graph")
    parser.add_argument("--opset", type=int, default=17, help="ONNX opset version")
    args = parser.parse_args()

    if not args.model.is_file():
        parser.error(f"no model file at {args.model}")
    try:
        model = load_model(args.model)
    except Exception as error:
        parser.error(
            f"could not load {args.model} as a DACERF, DACER or DSAC model (was it saved by another algorithm?): "
            f"{type(error).__name__}: {error}"
        )
    vec_normalize = None
    if args.vec_normalize is not None:
        if not args.vec_normalize.is_file():
            parser.error(f"no VecNormalize statistics file at {args.vec_normalize}")
        # What VecNormalize.load does, without an environment to wrap: only the statistics are needed
        try:
            with open(args.vec_normalize, "rb") as file:
                vec_normalize = pickle.load(file)
        except Exception as error:
            parser.error(
                f"could not read {args.vec_normalize} as VecNormalize statistics (a file written by VecNormalize.save): "
                f"{type(error).__name__}: {error}"
            )
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
