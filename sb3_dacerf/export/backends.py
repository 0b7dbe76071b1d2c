"""
The two export formats: :func:`export_policy` traces an actor's deployment graph (``sb3_dacerf.export.wrappers``)
and writes it as ONNX (with the noise input's default value) or TorchScript (with the noise argument optional).
"""

import warnings
from pathlib import Path

import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from sb3_dacerf.common.utils import atomic_path
from sb3_dacerf.dacer.policies import DiffusionActor
from sb3_dacerf.dacerf.policies import FlowActor
from sb3_dacerf.dsac.policies import GaussianActor
from sb3_dacerf.export.wrappers import FlaggedPolicy, check_vec_normalize, exportable_policy

EXPORT_FORMATS = ("onnx", "torchscript")
# Observation spaces that SB3's ``preprocess_obs`` handles with traceable tensor operations
SUPPORTED_OBSERVATION_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)


def _check_finite(obs: th.Tensor) -> None:
    # obs * 0 is 0 for a finite entry and NaN for a NaN or infinite one: fewer interpreter steps than isfinite().all()
    if obs.is_floating_point() and float((obs * 0).sum()) != 0.0:
        raise ValueError(
            "the observation has NaN or infinite entries, from which the policy can only compute a meaningless action: "
            "replace them before calling the policy"
        )


class _ScriptedPolicy(nn.Module):
    """
    TorchScript entry point with ``a0`` optional: the graph traced without it (a0 = 0) or the one traced with it. An
    observation with NaN or infinite entries raises a ``ValueError``, which reaches the caller as ``torch.jit.Error``.
    """

    def __init__(self, deterministic: th.jit.ScriptModule, stochastic: th.jit.ScriptModule):
        super().__init__()
        self.deterministic = deterministic
        self.stochastic = stochastic

    def forward(self, obs: th.Tensor, a0: th.Tensor | None = None) -> th.Tensor:
        _check_finite(obs)
        if a0 is None:
            return self.deterministic(obs)
        return self.stochastic(obs, a0)


class _ScriptedDictPolicy(_ScriptedPolicy):
    """:class:`_ScriptedPolicy` for Dict observation spaces."""

    def forward(self, obs: dict[str, th.Tensor], a0: th.Tensor | None = None) -> th.Tensor:  # type: ignore[override]
        for value in obs.values():
            _check_finite(value)
        if a0 is None:
            return self.deterministic(obs)
        return self.stochastic(obs, a0)


class _ScriptedDiffusionPolicy(_ScriptedPolicy):
    """:class:`_ScriptedPolicy` of a DACER policy, whose optional second input is ``noise``."""

    def forward(self, obs: th.Tensor, noise: th.Tensor | None = None) -> th.Tensor:
        _check_finite(obs)
        if noise is None:
            return self.deterministic(obs)
        return self.stochastic(obs, noise)


class _ScriptedDiffusionDictPolicy(_ScriptedPolicy):
    """:class:`_ScriptedDiffusionPolicy` for Dict observation spaces."""

    def forward(self, obs: dict[str, th.Tensor], noise: th.Tensor | None = None) -> th.Tensor:  # type: ignore[override]
        for value in obs.values():
            _check_finite(value)
        if noise is None:
            return self.deterministic(obs)
        return self.stochastic(obs, noise)


#: The TorchScript entry point of each graph: (Dict observations?, noise input name) -> class
_SCRIPTED_POLICIES = {
    (False, "a0"): _ScriptedPolicy,
    (True, "a0"): _ScriptedDictPolicy,
    (False, "noise"): _ScriptedDiffusionPolicy,
    (True, "noise"): _ScriptedDiffusionDictPolicy,
}


def export_policy(
    model: BaseAlgorithm,
    path: str | Path,
    format: str = "onnx",
    n_sampling_steps: int | None = None,
    vec_normalize: VecNormalize | None = None,
    opset_version: int = 17,
) -> Path:
    """
    Export the policy of a DACER-F, DACER or DSAC model as a graph from raw observation to action in the environment's units.

    ONNX: inputs ``obs`` (or one input per key of a Dict observation space, named by the key) and the noise (DACERF:
    ``a0``, ``(batch, action_dim)``; DACER: ``noise``, ``(batch, n_diffusion_steps, action_dim)``; DSAC: ``noise``,
    ``(batch, action_dim)``), outputs ``action`` and ``finite``, batch dimension dynamic. ``finite`` ``(batch,)``
    is false where an observation has a NaN or infinite entry, and that row's action is NaN: check it before acting
    (ONNX graphs cannot raise). The noise defaults to zeros (an initializer that onnxruntime lets you override:
    ``session.run(None, {"obs": obs})`` is deterministic, ``{"obs": obs, "a0": a0}`` is not); a noise with a batch of 1
    is shared by all the observations. TorchScript: ``policy(obs)`` or ``policy(obs, noise)``, with ``obs`` a tensor
    or a dict of tensors; an observation with a NaN or infinite entry raises ``torch.jit.Error`` (the graph's
    ``ValueError``). Observations have the model's observation space layout (channel-first images, as after
    ``VecTransposeImage``) and dtype (``uint8`` images, ``int64`` discrete observations), with a leading batch
    dimension.

    :param model: A DACERF, DACER or DSAC model (trained or not)
    :param path: File to write (``.onnx`` or ``.pt`` by convention); its folder must exist. The file is written
        whole or not at all: it replaces an existing one only once complete
    :param format: ``"onnx"`` or ``"torchscript"``
    :param n_sampling_steps: DACERF: number of Euler steps, fixed in the graph (the model's ``n_sampling_steps`` by
        default). DACER: leave it out; its ``n_diffusion_steps`` reverse steps are fixed by its noise schedule. DSAC: leave
        it out
    :param vec_normalize: The VecNormalize wrapper the model was trained with (e.g. from ``load_vec_normalize``), if any:
        its observation normalisation is then applied inside the graph, so the graph takes raw observations; statistics
        of another observation layout are refused (:func:`check_vec_normalize`)
    :param opset_version: ONNX opset
    :return: The path written
    """
    if format not in EXPORT_FORMATS:
        raise ValueError(f"Unknown export format {format!r}: choose one of {EXPORT_FORMATS}")
    actor = getattr(model, "actor", None)
    if not isinstance(actor, (FlowActor, DiffusionActor, GaussianActor)):
        raise TypeError(
            f"export_policy exports DACERF, DACER and DSAC models (whose actor is a FlowActor, a DiffusionActor or a "
            "GaussianActor), "
            f"got a {type(model).__name__} model whose actor is a {type(actor).__name__}. "
            "For SB3's own algorithms see https://stable-baselines3.readthedocs.io/en/master/guide/export.html"
        )
    observation_space = model.observation_space
    subspaces = observation_space.spaces.values() if isinstance(observation_space, spaces.Dict) else [observation_space]
    if not all(isinstance(subspace, SUPPORTED_OBSERVATION_SPACES) for subspace in subspaces):
        raise TypeError(
            f"Cannot export a policy for the observation space {observation_space}: supported are Box, Discrete, "
            "MultiDiscrete and MultiBinary observations, and Dict spaces of them."
        )
    if vec_normalize is not None:
        check_vec_normalize(vec_normalize, observation_space)
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"Cannot write {path}: the folder {path.parent} does not exist")

    module = exportable_policy(actor, n_sampling_steps, vec_normalize)
    obs = model.policy.obs_to_tensor(observation_space.sample())[0]
    obs = {key: value.cpu() for key, value in obs.items()} if isinstance(obs, dict) else obs.cpu()
    noise = th.zeros(module.default_noise_shape)
    if format == "torchscript":
        scripted_class = _SCRIPTED_POLICIES[module.obs_keys is not None, module.noise_name]
        scripted = th.jit.script(scripted_class(th.jit.trace(module, (obs,)), th.jit.trace(module, (obs, noise))))
        # Written whole or not at all: a failed write leaves a previous file at `path` as it was
        with atomic_path(path) as temporary:
            th.jit.save(scripted, str(temporary))
        return path

    import onnx  # the optional "export" extra: imported only here, so that TorchScript export does not need it

    obs_names = ["obs"] if module.obs_keys is None else module.obs_keys
    # The noise's batch is its own dimension: 1 (one noise for the whole batch, as the default) or the observations'
    noise_name = module.noise_name
    dynamic_axes = {**{name: {0: "batch"} for name in [*obs_names, "action", "finite"]}, noise_name: {0: f"{noise_name}_batch"}}
    # Written whole or not at all: a failed write leaves a previous file at `path` as it was
    with atomic_path(path) as temporary:
        with warnings.catch_warnings():
            # torch>=2.9 deprecates the TorchScript-based exporter; the torch.export one needs onnxscript, not a dependency
            warnings.simplefilter("ignore", DeprecationWarning)
            th.onnx.export(
                FlaggedPolicy(module),
                (obs, noise),
                str(temporary),
                dynamo=False,
                input_names=[*obs_names, noise_name],
                output_names=["action", "finite"],
                dynamic_axes=dynamic_axes,
                opset_version=opset_version,
            )
        graph = onnx.load(str(temporary))
        # An initializer with an input's name is that input's default value: zeros, deterministic unless overridden
        graph.graph.initializer.append(onnx.numpy_helper.from_array(noise.numpy(), noise_name))
        onnx.checker.check_model(graph)
        onnx.save(graph, str(temporary))
    return path
