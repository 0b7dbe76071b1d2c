"""
Export a DACER-F policy to ONNX or TorchScript for deployment without Python, SB3 or this package.

The exported graph takes the raw observation (SB3's preprocessing inside: image scaling, one-hot encoding,
Dict features extraction, and optionally VecNormalize's observation normalisation) and returns the action
in the environment's units, as ``model.predict`` does. The flow's starting point ``a0`` is an optional second
input: left out, it is 0 (``deterministic=True``); given ``a0 ~ N(0, I)``, the policy samples stochastically.

    python -m sb3_dacerf.export MODEL.zip --format onnx --out policy.onnx
    python -m sb3_dacerf.export MODEL.zip --format torchscript --vec-normalize vecnormalize.pkl
"""

import argparse
import copy
import pickle
import warnings
from pathlib import Path

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.type_aliases import PyTorchObs
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from sb3_dacerf.common.utils import atomic_path
from sb3_dacerf.dacerf.dacerf import DACERF
from sb3_dacerf.dacerf.policies import VelocityField

EXPORT_FORMATS = ("onnx", "torchscript")
# Observation spaces that SB3's ``preprocess_obs`` handles with traceable tensor operations
SUPPORTED_OBSERVATION_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)


class ExportablePolicy(nn.Module):
    """
    The deployment graph of a DACER-F actor, on a CPU copy of it:
    ``action = low + (clip(Euler_N(a0; s), -1, 1) + 1) / 2 * (high - low)`` with ``s`` the raw observation,
    normalised as VecNormalize does when its statistics are given, then preprocessed as by ``model.predict``.
    It computes what ``VelocityField.sample`` does, up to float rounding, with the velocity network's first
    layer split by input for a smaller graph.

    :param actor: The flow actor (``model.actor``)
    :param n_sampling_steps: Number of Euler steps, fixed in the graph (the actor's ``n_sampling_steps`` by default)
    :param vec_normalize: VecNormalize wrapper the model was trained with:
        its observation normalisation is baked into the graph; rewards play no part in acting
    """

    def __init__(self, actor: VelocityField, n_sampling_steps: int | None = None, vec_normalize: VecNormalize | None = None):
        super().__init__()
        # A copy, so that exporting neither moves nor switches the mode of the model being trained
        self.actor = copy.deepcopy(actor).cpu().requires_grad_(False)
        self.actor.set_training_mode(False)
        self.n_sampling_steps = actor.n_sampling_steps if n_sampling_steps is None else n_sampling_steps
        if isinstance(self.n_sampling_steps, bool) or not isinstance(self.n_sampling_steps, int) or self.n_sampling_steps < 1:
            raise ValueError(f"n_sampling_steps must be an integer >= 1, got {self.n_sampling_steps!r}")
        step = 1.0 / self.n_sampling_steps
        # Euler steps a <- a + v / N: the last layer is scaled by 1 / N so that the network outputs the step itself
        last_layer = self.actor.velocity_net[-1]
        last_layer.weight.mul_(step)
        last_layer.bias.mul_(step)
        # The first layer, split by input ([features, actions, time]): the state term is one Gemm, the time term a
        # constant, and a (1, action_dim) a0 broadcasts over the batch; without a0 (= 0) the action term is left out
        first_layer = self.actor.velocity_net[0]
        state_weight, action_weight, time_weight = first_layer.weight.split(
            [self.actor.features_dim, self.actor.action_dim, 1], 1
        )
        self.register_buffer("state_weight", state_weight.t().contiguous())
        self.register_buffer("action_weight", action_weight.contiguous())
        self.register_buffer("time_weight", time_weight[:, 0].contiguous())
        self.register_buffer("first_bias", first_layer.bias.clone())
        self.velocity_tail = self.actor.velocity_net[1:]
        # SB3's unscaling low + 0.5 (a + 1) (high - low), as one multiply-add
        low, high = actor.action_space.low.astype(np.float64), actor.action_space.high.astype(np.float64)
        self.register_buffer("action_center", th.as_tensor((high + low) / 2, dtype=th.float32))
        self.register_buffer("action_half_range", th.as_tensor((high - low) / 2, dtype=th.float32))

        self.obs_keys = list(actor.observation_space.spaces) if isinstance(actor.observation_space, spaces.Dict) else None
        # Keys whose observations are normalised ("obs" for a non-Dict space), with their statistics as float64
        # buffers: VecNormalize normalises in float64 before SB3 casts to float32
        self.normalized_keys: list[str] = []
        if vec_normalize is not None and vec_normalize.norm_obs:
            if self.obs_keys is None:
                stats = {"obs": vec_normalize.obs_rms}
            else:
                stats = {key: vec_normalize.obs_rms[key] for key in vec_normalize.norm_obs_keys}
            for key, rms in stats.items():
                self.register_buffer(f"obs_mean_{key}", th.as_tensor(rms.mean, dtype=th.float64))
                self.register_buffer(f"obs_std_{key}", th.as_tensor(np.sqrt(rms.var + vec_normalize.epsilon), dtype=th.float64))
                self.normalized_keys.append(key)
            self.clip_obs = float(vec_normalize.clip_obs)

    def _normalize(self, obs: th.Tensor, key: str) -> th.Tensor:
        mean, std = getattr(self, f"obs_mean_{key}"), getattr(self, f"obs_std_{key}")
        return ((obs.double() - mean) / std).clamp(-self.clip_obs, self.clip_obs)

    def forward(self, obs: PyTorchObs, a0: th.Tensor | None = None) -> th.Tensor:
        """
        :param obs: Raw observations ``(batch, *obs_shape)``, or a dict of them for a Dict observation space
        :param a0: Starting points of the flow ``(batch, action_dim)``, or ``(1, action_dim)`` for all the batch;
            ``None`` for 0, the deterministic action
        :return: Actions in the environment's units ``(batch, action_dim)``
        """
        if isinstance(obs, dict):
            obs = {key: self._normalize(value, key) if key in self.normalized_keys else value for key, value in obs.items()}
        elif self.normalized_keys:
            obs = self._normalize(obs, "obs")
        features = self.actor.extract_features(obs, self.actor.features_extractor)
        # The Euler steps of VelocityField.sample from t = 0, unrolled (their number is fixed in the graph)
        actions = a0
        for k in range(self.n_sampling_steps):
            bias = self.first_bias if k == 0 else self.first_bias + (k / self.n_sampling_steps) * self.time_weight
            if actions is not None:
                bias = nn.functional.linear(actions, self.action_weight, bias)
            euler_step = self.velocity_tail(th.addmm(bias, features, self.state_weight))
            actions = euler_step if actions is None else actions + euler_step
        return th.addcmul(self.action_center, self.action_half_range, actions.clamp(-1.0, 1.0))


class _ScriptedPolicy(nn.Module):
    """TorchScript entry point with ``a0`` optional: the graph traced without it (a0 = 0) or the one traced with it."""

    def __init__(self, deterministic: th.jit.ScriptModule, stochastic: th.jit.ScriptModule):
        super().__init__()
        self.deterministic = deterministic
        self.stochastic = stochastic

    def forward(self, obs: th.Tensor, a0: th.Tensor | None = None) -> th.Tensor:
        if a0 is None:
            return self.deterministic(obs)
        return self.stochastic(obs, a0)


class _ScriptedDictPolicy(_ScriptedPolicy):
    """:class:`_ScriptedPolicy` for Dict observation spaces."""

    def forward(self, obs: dict[str, th.Tensor], a0: th.Tensor | None = None) -> th.Tensor:  # type: ignore[override]
        if a0 is None:
            return self.deterministic(obs)
        return self.stochastic(obs, a0)


def check_vec_normalize(vec_normalize: object, observation_space: spaces.Space) -> None:
    """
    Check that VecNormalize statistics fit a model's observations before they are baked into its graph.

    :param vec_normalize: What was given as the model's VecNormalize (statistics)
    :param observation_space: The model's observation space
    :raises TypeError: if ``vec_normalize`` is not a VecNormalize
    :raises ValueError: if the statistics normalise observations of another layout than the model's (another
        environment's statistics), naming both
    """
    if not isinstance(vec_normalize, VecNormalize):
        raise TypeError(
            f"vec_normalize must be a VecNormalize (e.g. VecNormalize.load(...), or a file written by VecNormalize.save), "
            f"got a {type(vec_normalize).__name__}"
        )
    if not getattr(vec_normalize, "norm_obs", False):
        return
    obs_rms = getattr(vec_normalize, "obs_rms", None)
    advice = "Give the statistics saved together with this model (RL Zoo: <log folder>/<env id>/vecnormalize.pkl)."
    if isinstance(observation_space, spaces.Dict):
        if not isinstance(obs_rms, dict):
            raise ValueError(
                f"The VecNormalize statistics normalise one observation array of shape "
                f"{np.shape(getattr(obs_rms, 'mean', None))} but the model takes Dict observations with keys "
                f"{list(observation_space.spaces)}. {advice}"
            )
        for key, rms in obs_rms.items():
            if key not in observation_space.spaces:
                raise ValueError(
                    f"The VecNormalize statistics normalise the observation key {key!r}, which the model does not have "
                    f"(its keys: {list(observation_space.spaces)}). {advice}"
                )
            if np.shape(rms.mean) != observation_space[key].shape:
                raise ValueError(
                    f"The VecNormalize statistics of the key {key!r} have shape {np.shape(rms.mean)} but the model's "
                    f"{key!r} observations have shape {observation_space[key].shape}. {advice}"
                )
        return
    if isinstance(obs_rms, dict):
        raise ValueError(
            f"The VecNormalize statistics are for Dict observations (keys {list(obs_rms)}) but the model takes one "
            f"observation array of shape {observation_space.shape}. {advice}"
        )
    if np.shape(getattr(obs_rms, "mean", None)) != observation_space.shape:
        raise ValueError(
            f"The VecNormalize statistics normalise observations of shape {np.shape(getattr(obs_rms, 'mean', None))} "
            f"but the model's observations have shape {observation_space.shape}. {advice}"
        )


def export_policy(
    model: BaseAlgorithm,
    path: str | Path,
    format: str = "onnx",
    n_sampling_steps: int | None = None,
    vec_normalize: VecNormalize | None = None,
    opset_version: int = 17,
) -> Path:
    """
    Export the policy of a DACER-F model as a graph from raw observation to action in the environment's units.

    ONNX: inputs ``obs`` (or one input per key of a Dict observation space, named by the key) and ``a0``,
    output ``action``, batch dimension dynamic. ``a0`` defaults to zeros (an initializer that onnxruntime
    lets you override: ``session.run(None, {"obs": obs})`` is deterministic, ``{"obs": obs, "a0": noise}`` is not).
    TorchScript: ``policy(obs)`` or ``policy(obs, a0)``, with ``obs`` a tensor or a dict of tensors.
    Observations have the model's observation space layout (channel-first images, as after ``VecTransposeImage``)
    and dtype (``uint8`` images, ``int64`` discrete observations), with a leading batch dimension.

    :param model: A DACERF model (trained or not)
    :param path: File to write (``.onnx`` or ``.pt`` by convention); its folder must exist. The file is written
        whole or not at all: it replaces an existing one only once complete
    :param format: ``"onnx"`` or ``"torchscript"``
    :param n_sampling_steps: Number of Euler steps, fixed in the graph (the model's ``n_sampling_steps`` by default)
    :param vec_normalize: The VecNormalize wrapper the model was trained with (e.g. from ``VecNormalize.load``), if any:
        its observation normalisation is then applied inside the graph, so the graph takes raw observations; statistics
        of another observation layout are refused (:func:`check_vec_normalize`)
    :param opset_version: ONNX opset
    :return: The path written
    """
    if format not in EXPORT_FORMATS:
        raise ValueError(f"Unknown export format {format!r}: choose one of {EXPORT_FORMATS}")
    actor = getattr(model, "actor", None)
    if not isinstance(actor, VelocityField):
        raise TypeError(
            f"export_policy exports DACERF models (a flow actor sb3_dacerf.dacerf.policies.VelocityField), "
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

    module = ExportablePolicy(actor, n_sampling_steps, vec_normalize)
    obs = model.policy.obs_to_tensor(observation_space.sample())[0]
    obs = {key: value.cpu() for key, value in obs.items()} if isinstance(obs, dict) else obs.cpu()
    a0 = th.zeros((1, actor.action_dim))
    if format == "torchscript":
        scripted_class = _ScriptedPolicy if module.obs_keys is None else _ScriptedDictPolicy
        scripted = th.jit.script(scripted_class(th.jit.trace(module, (obs,)), th.jit.trace(module, (obs, a0))))
        # Written whole or not at all: a failed write leaves a previous file at `path` as it was
        with atomic_path(path) as temporary:
            th.jit.save(scripted, str(temporary))
        return path

    import onnx  # the optional "export" extra: imported only here, so that TorchScript export does not need it

    obs_names = ["obs"] if module.obs_keys is None else module.obs_keys
    # a0's batch is its own dimension: 1 (one a0 for the whole batch, as the default) or the observations' batch
    dynamic_axes = {**{name: {0: "batch"} for name in [*obs_names, "action"]}, "a0": {0: "a0_batch"}}
    # Written whole or not at all: a failed write leaves a previous file at `path` as it was
    with atomic_path(path) as temporary:
        with warnings.catch_warnings():
            # torch>=2.9 deprecates the TorchScript-based exporter; the torch.export one needs onnxscript, not a dependency
            warnings.simplefilter("ignore", DeprecationWarning)
            th.onnx.export(
                module,
                (obs, a0),
                str(temporary),
                dynamo=False,
                input_names=[*obs_names, "a0"],
                output_names=["action"],
                dynamic_axes=dynamic_axes,
                opset_version=opset_version,
            )
        graph = onnx.load(str(temporary))
        # An initializer with an input's name is that input's default value: a0 = 0, deterministic unless overridden
        graph.graph.initializer.append(onnx.numpy_helper.from_array(np.zeros((1, actor.action_dim), dtype=np.float32), "a0"))
        onnx.checker.check_model(graph)
        onnx.save(graph, str(temporary))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(
        prog="python -m sb3_dacerf.export", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("model", type=Path, help="DACERF model saved with model.save() (.zip)")
    parser.add_argument("--format", choices=EXPORT_FORMATS, default="onnx")
    parser.add_argument("--out", type=Path, help="output file (default: the model's name with .onnx or .pt)")
    parser.add_argument("--n-sampling-steps", type=int, help="Euler steps fixed in the graph (default: the model's)")
    parser.add_argument("--vec-normalize", type=Path, help="VecNormalize statistics (.pkl) to bake into the graph")
    parser.add_argument("--opset", type=int, default=17, help="ONNX opset version")
    args = parser.parse_args()

    if not args.model.is_file():
        parser.error(f"no model file at {args.model}")
    try:
        model = DACERF.load(args.model, device="cpu")
    except Exception as error:
        parser.error(
            f"could not load {args.model} as a DACERF model (was it saved by another algorithm?): {type(error).__name__}: {error}"
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
    n_sampling_steps = model.actor.n_sampling_steps if args.n_sampling_steps is None else args.n_sampling_steps
    try:
        export_policy(model, out, args.format, n_sampling_steps, vec_normalize, args.opset)
    except (TypeError, ValueError, FileNotFoundError) as error:
        parser.error(str(error))
    print(f"Exported {args.model} ({args.format}, {n_sampling_steps} Euler step(s)) to {out}")


if __name__ == "__main__":
    main()
