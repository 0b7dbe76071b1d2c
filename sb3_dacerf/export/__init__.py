"""
Export a DACER-F, DACER or DSAC policy to ONNX or TorchScript: one graph from the raw observation (SB3's preprocessing
and optionally VecNormalize's observation normalisation inside) to the action in the environment's units. The noise
is an optional second input, 0 (deterministic) when left out: DACER-F's ``a0`` ``(batch, action_dim)``; DACER's
``noise`` ``(batch, n_diffusion_steps, action_dim)``; DSAC's ``noise`` ``(batch, action_dim)``, the ``ξ`` of
``tanh(μ + σ ξ)``; a batch of 1 is shared by all the observations. The command reads the model and the statistics
without running code from them (see ``docs/guide/loading.md``):

    python -m sb3_dacerf.export MODEL.zip --format onnx --out policy.onnx
    python -m sb3_dacerf.export MODEL.zip --format torchscript --vec-normalize vecnormalize.json
"""

import argparse
import copy
import pickle
import warnings
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.type_aliases import PyTorchObs
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from sb3_dacerf import DACER, DACERF, DSAC
from sb3_dacerf.common.persistence import check_sha256, load_vec_normalize, saved_algorithm_name
from sb3_dacerf.common.policies import GenerativeActor
from sb3_dacerf.common.utils import atomic_path
from sb3_dacerf.common.vec_normalize import MaskedVecNormalize
from sb3_dacerf.dacer.policies import DiffusionActor
from sb3_dacerf.dacerf.policies import FlowActor
from sb3_dacerf.dsac.policies import GaussianActor

#: The formats of :func:`export_policy`
EXPORT_FORMATS = ("onnx", "torchscript")
#: Observation spaces that SB3's ``preprocess_obs`` handles with traceable tensor operations (and Dict spaces of them)
SUPPORTED_OBSERVATION_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)


class ExportablePolicy(nn.Module, ABC):
    """
    The deployment graph of an actor, on a CPU copy of it: the raw observation, normalised as VecNormalize does when
    its statistics are given and preprocessed as by ``model.predict``, to ``low + (a + 1) / 2 * (high - low)``,
    ``a = clip(generate(features, noise), -1, 1)``. :func:`exportable_policy` picks the subclass of an actor.

    :param actor: The actor (``model.actor``)
    :param vec_normalize: The VecNormalize the model was trained with: its observation normalisation goes into the graph
    """

    #: Name of the noise input of ONNX graphs (and of the second argument of TorchScript ones)
    noise_name: ClassVar[str] = "noise"
    action_center: th.Tensor
    action_half_range: th.Tensor
    state_weight: th.Tensor
    action_weight: th.Tensor

    def __init__(self, actor: GenerativeActor | GaussianActor, vec_normalize: VecNormalize | None = None):
        super().__init__()
        # A copy, so that exporting neither moves nor switches the mode of the model being trained
        self.actor = copy.deepcopy(actor).cpu().requires_grad_(False)
        self.actor.set_training_mode(False)
        low, high = actor.action_space.low.astype(np.float64), actor.action_space.high.astype(np.float64)
        self.register_buffer("action_center", th.as_tensor((high + low) / 2, dtype=th.float32))
        self.register_buffer("action_half_range", th.as_tensor((high - low) / 2, dtype=th.float32))
        self.obs_keys = list(actor.observation_space.spaces) if isinstance(actor.observation_space, spaces.Dict) else None
        # The normalised keys ("obs" for a non-Dict space), their statistics float64 buffers: VecNormalize normalises in
        # float64 before SB3 casts to float32
        self.normalized_keys: list[str] = []
        if vec_normalize is not None and vec_normalize.norm_obs:
            obs_rms = vec_normalize.obs_rms
            for key, rms in (obs_rms if isinstance(obs_rms, dict) else {"obs": obs_rms}).items():
                self.register_buffer(f"obs_mean_{key}", th.as_tensor(rms.mean, dtype=th.float64))
                self.register_buffer(f"obs_std_{key}", th.as_tensor(np.sqrt(rms.var + vec_normalize.epsilon), dtype=th.float64))
                self.normalized_keys.append(key)
            self.clip_obs = float(vec_normalize.clip_obs)
        # MaskedVecNormalize's table of optional rows (empty rows zeros, the mask kept 0 / 1): (start, count, size)
        self.masked_rows: tuple[int, ...] | None = None
        # (getattr on a VecNormalize without its environment would recurse in VecEnvWrapper.__getattr__)
        if self.normalized_keys == ["obs"] and isinstance(vec_normalize, MaskedVecNormalize):
            self.masked_rows = tuple(int(value) for value in vec_normalize.rows)

    def _split_first_layer(self, other_size: int) -> tuple[th.Tensor, th.Tensor]:
        """Registers the state and action weights of the network's first layer; returns the third input's and the bias."""
        first_layer = _linear(self.actor.network[0])
        state_weight, action_weight, other_weight = first_layer.weight.split(
            [self.actor.features_dim, self.actor.action_dim, other_size], 1
        )
        self.register_buffer("state_weight", state_weight.t().contiguous())
        self.register_buffer("action_weight", action_weight.contiguous())
        return other_weight, first_layer.bias

    def _normalize(self, obs: th.Tensor, key: str) -> th.Tensor:
        mean, std = getattr(self, f"obs_mean_{key}"), getattr(self, f"obs_std_{key}")
        normalized = ((obs.double() - mean) / std).clamp(-self.clip_obs, self.clip_obs)
        if self.masked_rows is None:
            return normalized
        # As MaskedVecNormalize: a row whose mask is 0 becomes zeros, the mask entry stays 0 / 1
        start, count, size = self.masked_rows
        end = start + count * size
        table = normalized[..., start:end].reshape(*normalized.shape[:-1], count, size)
        present = obs[..., start:end].reshape(*obs.shape[:-1], count, size)[..., -1:].double().gt(0.5).double()
        table = th.cat([table[..., :-1] * present, present], dim=-1).reshape(*normalized.shape[:-1], count * size)
        return th.cat([normalized[..., :start], table, normalized[..., end:]], dim=-1)

    @abstractmethod
    def generate(self, features: th.Tensor, noise: th.Tensor | None) -> th.Tensor:
        """``actor.sample(features, noise)`` (``None``: zeros) in [-1, 1] before the clipping, for a small traced graph."""

    def forward(self, obs: PyTorchObs, noise: th.Tensor | None = None) -> th.Tensor:
        """Actions ``(batch, action_dim)`` in the environment's units for raw observations and the noise (or ``None``)."""
        if isinstance(obs, dict):
            obs = {key: self._normalize(value, key) if key in self.normalized_keys else value for key, value in obs.items()}
        elif self.normalized_keys:
            obs = self._normalize(obs, "obs")
        actions = self.generate(self.actor.extract_features(obs, self.actor.features_extractor), noise)
        return th.addcmul(self.action_center, self.action_half_range, actions.clamp(-1.0, 1.0))


class ExportableFlowPolicy(ExportablePolicy):
    """
    DACER-F: the ``n_sampling_steps`` Euler steps of ``FlowActor.sample`` from ``a0``, unrolled.

    :param n_sampling_steps: Number of Euler steps, fixed in the graph (the actor's by default)
    """

    noise_name = "a0"
    actor: FlowActor
    time_weight: th.Tensor
    first_bias: th.Tensor

    def __init__(self, actor: FlowActor, n_sampling_steps: int | None = None, vec_normalize: VecNormalize | None = None):
        super().__init__(actor, vec_normalize)
        self.n_sampling_steps = actor.n_sampling_steps if n_sampling_steps is None else n_sampling_steps
        if isinstance(self.n_sampling_steps, bool) or not isinstance(self.n_sampling_steps, int) or self.n_sampling_steps < 1:
            raise ValueError(f"n_sampling_steps must be an integer >= 1, got {self.n_sampling_steps!r}")
        # Euler steps a <- a + v / N: the last layer is scaled by 1 / N so that the network outputs the step itself
        last_layer = _linear(self.actor.network[-1])
        last_layer.weight.mul_(1.0 / self.n_sampling_steps)
        last_layer.bias.mul_(1.0 / self.n_sampling_steps)
        # The first layer by input: the state term one Gemm, the time term a constant, the action term left out without a0
        time_weight, bias = self._split_first_layer(1)
        self.register_buffer("time_weight", time_weight[:, 0].contiguous())
        self.register_buffer("first_bias", bias.clone())
        self.tail = self.actor.network[1:]

    def generate(self, features: th.Tensor, noise: th.Tensor | None) -> th.Tensor:
        actions = noise
        for k in range(self.n_sampling_steps):
            bias = self.first_bias if k == 0 else self.first_bias + (k / self.n_sampling_steps) * self.time_weight
            if actions is not None:
                bias = nn.functional.linear(actions, self.action_weight, bias)
            euler_step = self.tail(th.addmm(bias, features, self.state_weight))
            actions = euler_step if actions is None else actions + euler_step
        assert actions is not None  # n_sampling_steps >= 1
        return actions


class ExportableDiffusionPolicy(ExportablePolicy):
    """DACER: the ``n_diffusion_steps`` reverse steps of ``DiffusionActor.sample``, unrolled, with the time embeddings'
    terms as constants."""

    actor: DiffusionActor
    time_terms: th.Tensor

    def __init__(self, actor: DiffusionActor, vec_normalize: VecNormalize | None = None):
        super().__init__(actor, vec_normalize)
        self.reverse_coefficients = list(self.actor.reverse_coefficients)
        time_weight, bias = self._split_first_layer(self.actor.time_embedding_dim)
        with th.no_grad():  # the time term of the first layer at each step, with its bias: (n_diffusion_steps, hidden)
            self.register_buffer("time_terms", nn.functional.linear(self.actor.time_embeddings(), time_weight, bias).contiguous())
        self.tail = self.actor.network[1:]

    def generate(self, features: th.Tensor, noise: th.Tensor | None) -> th.Tensor:
        # From t = T - 1 down to 0; without noise, x_T = 0 and the terms of the action and posterior noise are left out
        state_term = features @ self.state_weight
        actions = None if noise is None else noise[:, 0]  # x_T = noise[:, 0], as in DiffusionActor.sample
        for t in reversed(range(len(self.reverse_coefficients))):
            c0, c1, m0, m1, std = self.reverse_coefficients[t]
            hidden = state_term + self.time_terms[t]
            if actions is None:
                actions = m0 * (-c1 * self.tail(hidden)).clamp(-1.0, 1.0)
            else:
                predicted_noise = self.tail(hidden + nn.functional.linear(actions, self.action_weight))
                actions = m0 * (c0 * actions - c1 * predicted_noise).clamp(-1.0, 1.0) + m1 * actions
            if noise is not None and t > 0:
                actions = actions + std * noise[:, t]
        assert actions is not None  # n_diffusion_steps >= 1
        return actions


class ExportableGaussianPolicy(ExportablePolicy):
    """DSAC: ``tanh(μ)`` (no noise) or ``tanh(μ + σ ξ)`` (noise ``ξ``), as ``GaussianActor.sample``."""

    actor: GaussianActor

    def generate(self, features: th.Tensor, noise: th.Tensor | None) -> th.Tensor:
        mean, log_std = self.actor.network(features).chunk(2, dim=-1)
        if noise is None:
            return th.tanh(mean)
        return th.tanh(mean + log_std.clamp(self.actor.log_std_min, self.actor.log_std_max).exp() * noise)


class _FlaggedPolicy(nn.Module):
    """The ONNX graph, which cannot raise: ``(action, finite)``, ``finite[i]`` false and ``action[i]`` NaN where
    observation ``i`` has a NaN or infinite entry."""

    def __init__(self, policy: ExportablePolicy):
        super().__init__()
        self.policy = policy

    def forward(self, obs: PyTorchObs, noise: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        # obs * 0 is 0 for a finite entry and NaN for a NaN or infinite one, so each row's sum is 0 or NaN: added to
        # the action it makes the row NaN, compared with 0 it is the flag (fewer graph nodes than IsInf / IsNaN / Where)
        values = list(obs.values()) if isinstance(obs, dict) else [obs]
        poison = [(v * 0).reshape(v.shape[0], -1).sum(dim=1, keepdim=True) for v in values if v.is_floating_point()]
        actions = self.policy(obs, noise)
        if not poison:  # integer observations (images, discrete) are always finite
            return actions, th.ones(actions.shape[0], dtype=th.bool, device=actions.device)
        total = poison[0] if len(poison) == 1 else th.cat(poison, dim=1).sum(dim=1, keepdim=True)
        return actions + total.to(actions.dtype), total[:, 0] == 0


def _linear(layer: nn.Module) -> nn.Linear:
    if not isinstance(layer, nn.Linear):
        raise TypeError(f"The actor's network must start and end with nn.Linear layers, got a {type(layer).__name__}")
    return layer


def exportable_policy(
    actor: GenerativeActor | GaussianActor, n_sampling_steps: int | None = None, vec_normalize: VecNormalize | None = None
) -> ExportablePolicy:
    """
    The deployment graph of ``model.actor`` of a DACERF, DACER or DSAC model.

    :param n_sampling_steps: DACERF: Euler steps fixed in the graph (the actor's by default); DACER: its
        ``n_diffusion_steps`` or nothing; DSAC: nothing
    :param vec_normalize: The VecNormalize the model was trained with, if any
    """
    if isinstance(actor, FlowActor):
        return ExportableFlowPolicy(actor, n_sampling_steps, vec_normalize)
    if isinstance(actor, DiffusionActor) and n_sampling_steps in (None, actor.n_diffusion_steps):
        return ExportableDiffusionPolicy(actor, vec_normalize)
    if isinstance(actor, GaussianActor) and n_sampling_steps is None:
        return ExportableGaussianPolicy(actor, vec_normalize)
    if isinstance(actor, DiffusionActor):
        raise ValueError(
            f"n_sampling_steps={n_sampling_steps!r}: a DACER policy runs the {actor.n_diffusion_steps} reverse steps "
            "of the noise schedule it was trained with; leave n_sampling_steps out (a DACERF option)."
        )
    if isinstance(actor, GaussianActor):
        raise ValueError(
            f"n_sampling_steps={n_sampling_steps!r}: a DSAC policy computes its action in one network call; leave "
            "n_sampling_steps out (a DACERF option)."
        )
    raise TypeError(
        "export_policy exports DACERF, DACER and DSAC models (whose actor is a FlowActor, a DiffusionActor or a "
        f"GaussianActor), got an actor of type {type(actor).__name__}. "
        "For SB3's own algorithms see https://stable-baselines3.readthedocs.io/en/master/guide/export.html"
    )


def check_vec_normalize(vec_normalize: object, observation_space: spaces.Space) -> None:
    """
    Check that VecNormalize statistics fit a model's observation space before they are baked into its graph.

    :raises TypeError: ``vec_normalize`` is not a VecNormalize
    :raises ValueError: the statistics normalise observations of another layout (naming both)
    """
    if not isinstance(vec_normalize, VecNormalize):
        raise TypeError(
            "vec_normalize must be a VecNormalize (e.g. VecNormalize.load(...), or a file written by VecNormalize.save), "
            f"got a {type(vec_normalize).__name__}"
        )
    if not getattr(vec_normalize, "norm_obs", False):
        return
    obs_rms = getattr(vec_normalize, "obs_rms", None)
    # The shapes of the statistics and of the model's observations: one shape, or one per key of a Dict space
    shapes: Any = {k: _mean_shape(r) for k, r in obs_rms.items()} if isinstance(obs_rms, dict) else _mean_shape(obs_rms)
    if isinstance(observation_space, spaces.Dict):
        expected: Any = {key: space.shape for key, space in observation_space.spaces.items()}
        fits = isinstance(shapes, dict) and all(expected.get(key) == shape for key, shape in shapes.items())
    else:
        expected = observation_space.shape
        fits = shapes == expected
    if not fits:
        raise ValueError(
            f"The VecNormalize statistics normalise observations of shape {shapes} but the model's observations have "
            f"shape {expected}. Give the statistics saved together with this model (RL Zoo: <log folder>/<env id>/"
            "vecnormalize.pkl)."
        )


def _mean_shape(rms: object) -> tuple[int, ...]:
    return np.asarray(getattr(rms, "mean", None)).shape  # () when there is none


def _finite(obs: th.Tensor) -> th.Tensor:
    # obs * 0 is 0 for a finite entry and NaN for a NaN or infinite one: fewer interpreter steps than isfinite().all()
    if obs.is_floating_point() and float((obs * 0).sum()) != 0.0:
        raise ValueError(
            "the observation has NaN or infinite entries, from which the policy can only compute a meaningless action: "
            "replace them before calling the policy"
        )
    return obs


def _finite_dict(obs: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
    for value in obs.values():
        _finite(value)
    return obs


class _Scripted(nn.Module):
    """TorchScript entry point: the graph traced without the noise or the one traced with it; a ``ValueError`` for
    non-finite observations. The subclasses differ in the observation's type and the noise's name."""

    def __init__(self, deterministic: th.jit.ScriptModule, stochastic: th.jit.ScriptModule):
        super().__init__()
        self.deterministic, self.stochastic = deterministic, stochastic


class _ScriptedFlow(_Scripted):
    def forward(self, obs: th.Tensor, a0: th.Tensor | None = None) -> th.Tensor:
        return self.deterministic(_finite(obs)) if a0 is None else self.stochastic(_finite(obs), a0)


class _ScriptedFlowDict(_Scripted):
    def forward(self, obs: dict[str, th.Tensor], a0: th.Tensor | None = None) -> th.Tensor:
        return self.deterministic(_finite_dict(obs)) if a0 is None else self.stochastic(_finite_dict(obs), a0)


class _ScriptedNoise(_Scripted):
    def forward(self, obs: th.Tensor, noise: th.Tensor | None = None) -> th.Tensor:
        return self.deterministic(_finite(obs)) if noise is None else self.stochastic(_finite(obs), noise)


class _ScriptedNoiseDict(_Scripted):
    def forward(self, obs: dict[str, th.Tensor], noise: th.Tensor | None = None) -> th.Tensor:
        return self.deterministic(_finite_dict(obs)) if noise is None else self.stochastic(_finite_dict(obs), noise)


def export_policy(
    model: BaseAlgorithm,
    path: str | Path,
    format: str = "onnx",
    n_sampling_steps: int | None = None,
    vec_normalize: VecNormalize | None = None,
    opset_version: int = 17,
) -> Path:
    """
    Export the policy of a DACER-F, DACER or DSAC model as a graph from raw observation to action.

    ONNX: inputs ``obs`` (or one per key of a Dict observation space) and the noise (``a0`` or ``noise``, zeros by
    default), outputs ``action`` and ``finite``, false (and the action NaN) for a row with a NaN or infinite entry.
    TorchScript: ``policy(obs)`` or ``policy(obs, noise)``; a non-finite observation raises ``torch.jit.Error``.
    Observations have the model's observation space layout and dtype, with a leading batch dimension.

    :param model: A DACERF, DACER or DSAC model
    :param path: File to write (``.onnx`` or ``.pt``), in an existing folder; written whole or not at all
    :param format: ``"onnx"`` or ``"torchscript"``
    :param n_sampling_steps: DACERF: Euler steps, fixed in the graph (the model's by default); not for DACER or DSAC
    :param vec_normalize: The VecNormalize the model was trained with, if any: its observation normalisation goes into
        the graph, which then takes raw observations (statistics of another layout are refused)
    :param opset_version: ONNX opset
    :return: The path written
    """
    if format not in EXPORT_FORMATS:
        raise ValueError(f"Unknown export format {format!r}: choose one of {EXPORT_FORMATS}")
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

    module = exportable_policy(getattr(model, "actor", None), n_sampling_steps, vec_normalize)  # type: ignore[arg-type]
    obs = model.policy.obs_to_tensor(observation_space.sample())[0]
    obs = {key: value.cpu() for key, value in obs.items()} if isinstance(obs, dict) else obs.cpu()
    noise = th.zeros(1, *module.actor.noise_shape)  # the default: one noise for the whole batch
    if format == "torchscript":
        classes = (_ScriptedFlow, _ScriptedFlowDict) if module.noise_name == "a0" else (_ScriptedNoise, _ScriptedNoiseDict)
        scripted = classes[module.obs_keys is not None]
        graph = th.jit.script(scripted(th.jit.trace(module, (obs,)), th.jit.trace(module, (obs, noise))))
        with atomic_path(path) as temporary:
            th.jit.save(graph, str(temporary))
        return path

    import onnx  # the optional "export" extra, which TorchScript export does not need

    obs_names = ["obs"] if module.obs_keys is None else module.obs_keys
    # The noise's batch is its own dimension: 1 (one noise for the whole batch, as the default) or the observations'
    name = module.noise_name
    dynamic_axes = {**{key: {0: "batch"} for key in [*obs_names, "action", "finite"]}, name: {0: f"{name}_batch"}}
    with atomic_path(path) as temporary:
        with warnings.catch_warnings():
            # torch>=2.9 deprecates the TorchScript-based exporter; the torch.export one needs onnxscript, not a dependency
            warnings.simplefilter("ignore", DeprecationWarning)
            th.onnx.export(
                _FlaggedPolicy(module),
                (obs, noise),
                str(temporary),
                dynamo=False,
                input_names=[*obs_names, name],
                output_names=["action", "finite"],
                dynamic_axes=dynamic_axes,
                opset_version=opset_version,
            )
        onnx_model = onnx.load(str(temporary))
        # An initializer with an input's name is that input's default value: zeros, deterministic unless overridden
        onnx_model.graph.initializer.append(onnx.numpy_helper.from_array(noise.numpy(), name))
        onnx.checker.check_model(onnx_model)
        onnx.save(onnx_model, str(temporary))
    return path


def load_model(path: Path, unsafe_run_code_from_file: bool = False) -> DACERF | DACER | DSAC:
    """
    Load a DACERF, DACER or DSAC model on the CPU, the algorithm read from the file's JSON, running no code from the
    file unless ``unsafe_run_code_from_file``. A file listed in a ``SHA256SUMS`` beside it must match its checksum.

    :raises ValueError: the file holds another algorithm's model (naming it), or does not match its checksum
    """
    check_sha256(path)
    algorithm = saved_algorithm_name(path) or "dacerf"
    algorithms: dict[str, type[DACERF | DACER | DSAC]] = {"dacerf": DACERF, "dacer": DACER, "dsac": DSAC}
    if algorithm not in algorithms:
        raise ValueError(f"{path} holds a {algorithm.upper()} model: the command exports DACERF, DACER and DSAC models")
    return algorithms[algorithm].load(path, device="cpu", unsafe_run_code_from_file=unsafe_run_code_from_file)


def _load_statistics(path: Path, unsafe_run_code_from_file: bool) -> VecNormalize:
    """The JSON of ``save_vec_normalize``, or, only if ``unsafe_run_code_from_file``, a ``VecNormalize.save`` pickle."""
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
    parser.add_argument("--n-sampling-steps", type=int, help="DACERF: Euler steps fixed in the graph (default: the model's)")
    parser.add_argument("--vec-normalize", type=Path, help="observation statistics (.json of save_vec_normalize) to bake in")
    parser.add_argument("--opset", type=int, default=17, help="ONNX opset version")
    parser.add_argument(
        "--unsafe-run-code-from-file",
        action="store_true",
        help="also read files that need unpickling (a model saved by another package, VecNormalize .pkl statistics): "
        "a crafted file runs any code it holds. Only for files you made or trust",
    )
    args = parser.parse_args()
    if not args.model.is_file():
        parser.error(f"no model file at {args.model}")
    try:
        model = load_model(args.model, args.unsafe_run_code_from_file)
    except (OSError, ValueError, KeyError, RuntimeError) as error:
        parser.error(f"could not load {args.model} as a DACERF, DACER or DSAC model: {type(error).__name__}: {error}")
    vec_normalize = None
    if args.vec_normalize is not None:
        if not args.vec_normalize.is_file():
            parser.error(f"no VecNormalize statistics file at {args.vec_normalize}")
        try:
            vec_normalize = _load_statistics(args.vec_normalize, args.unsafe_run_code_from_file)
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
        steps = f"{args.n_sampling_steps or model.actor.n_sampling_steps} Euler step(s)"
    print(f"Exported {args.model} ({args.format}, {steps}) to {out}")
