"""
Export a DACER-F, DACER or DSAC policy to ONNX or TorchScript for deployment without Python, SB3 or this package.

The exported graph takes the raw observation (SB3's preprocessing inside: image scaling, one-hot encoding,
Dict features extraction, and optionally VecNormalize's observation normalisation) and returns the action
in the environment's units, as ``model.predict`` does. The generator's noise is an optional second input: left out,
it is 0 (``deterministic=True``); given standard normal noise, the policy samples stochastically (without the
exploration noise of rollouts). DACER-F's noise ``a0`` is the flow's starting point, ``(batch, action_dim)``; DACER's
``noise``, ``(batch, n_diffusion_steps, action_dim)``, holds the start and the posterior noise of each reverse step
(:class:`sb3_dacerf.dacer.policies.DiffusionActor`); DSAC's ``noise``, ``(batch, action_dim)``, is the standard normal
``ξ`` of its tanh-Gaussian action ``tanh(μ + σ ξ)``. Any of them may have a batch of 1, shared by all the observations.
Observations with NaN or infinite entries are refused: a TorchScript policy raises, an ONNX graph returns a second
output ``finite``, false for those rows, whose actions are NaN.

The package holds the graphs (``sb3_dacerf.export.wrappers``), the ONNX and TorchScript writers
(``sb3_dacerf.export.backends``) and the command line (``sb3_dacerf.export.cli``); everything public is imported here:

    python -m sb3_dacerf.export MODEL.zip --format onnx --out policy.onnx
    python -m sb3_dacerf.export MODEL.zip --format torchscript --vec-normalize vecnormalize.json
"""

from sb3_dacerf.export.backends import EXPORT_FORMATS, SUPPORTED_OBSERVATION_SPACES, export_policy
from sb3_dacerf.export.cli import load_model, main
from sb3_dacerf.export.wrappers import (
    ExportableDiffusionPolicy,
    ExportableFlowPolicy,
    ExportableGaussianPolicy,
    ExportablePolicy,
    check_vec_normalize,
    exportable_policy,
)

__all__ = [
    "EXPORT_FORMATS",
    "SUPPORTED_OBSERVATION_SPACES",
    "ExportableDiffusionPolicy",
    "ExportableFlowPolicy",
    "ExportableGaussianPolicy",
    "ExportablePolicy",
    "check_vec_normalize",
    "export_policy",
    "exportable_policy",
    "load_model",
    "main",
]
