"""
The deployment graphs of the package's actors: :class:`ExportablePolicy` (raw observation in, action in the
environment's units out, VecNormalize's observation normalisation optionally inside) and its subclasses for DACER-F's
flow and DACER's diffusion actor; :func:`check_vec_normalize` checks statistics before they are baked in.
"""

import copy
from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import PyTorchObs
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from sb3_dacerf.common.policies import GenerativeActor
from sb3_dacerf.common.vec_normalize import MaskedVecNormalize
from sb3_dacerf.dacer.policies import DiffusionActor
from sb3_dacerf.dacerf.policies import FlowActor
from sb3_dacerf.dsac.policies import GaussianActor


class ExportablePolicy(nn.Module, ABC):
    """
    The deployment graph of a generative actor, on a CPU copy of it: ``action = low + (a + 1) / 2 * (high - low)``,
    ``a = clip(generate(features(s), noise), -1, 1)`` with ``s`` the raw observation, normalised as VecNormalize
    does when its statistics are given, then preprocessed as by ``model.predict``. Subclasses write ``generate``
    for their actor: :class:`ExportableFlowPolicy` (DACERF), :class:`ExportableDiffusionPolicy` (DACER);
    :func:`exportable_policy` picks the one of an actor.

    :param actor: The actor (``model.actor``)
    :param vec_normalize: VecNormalize wrapper the model was trained with:
        its observation normalisation is baked into the graph; rewards play no part in acting
    """

    #: Name of the noise input of ONNX graphs (and of the second argument of TorchScript ones)
    noise_name: ClassVar[str]

    # Buffers (registered in __init__)
    action_center: th.Tensor
    action_half_range: th.Tensor

    def __init__(self, actor: GenerativeActor | GaussianActor, vec_normalize: VecNormalize | None = None):
        super().__init__()
        # A copy, so that exporting neither moves nor switches the mode of the model being trained
        self.actor = copy.deepcopy(actor).cpu().requires_grad_(False)
        self.actor.set_training_mode(False)
        # SB3's unscaling low + 0.5 (a + 1) (high - low), as one multiply-add
        low, high = actor.action_space.low.astype(np.float64), actor.action_space.high.astype(np.float64)
        self.register_buffer("action_center", th.as_tensor((high + low) / 2, dtype=th.float32))
        self.register_buffer("action_half_range", th.as_tensor((high - low) / 2, dtype=th.float32))

        self.obs_keys = list(actor.observation_space.spaces) if isinstance(actor.observation_space, spaces.Dict) else None
        # Keys whose observations are normalised ("obs" for a non-Dict space), with their statistics as float64
        # buffers: VecNormalize normalises in float64 before SB3 casts to float32
        self.normalized_keys: list[str] = []
        if vec_normalize is not None and vec_normalize.norm_obs:
            obs_rms = vec_normalize.obs_rms
            # A dict of the normalised keys' statistics for Dict observations (check_vec_normalize checks the layout)
            stats = dict(obs_rms) if isinstance(obs_rms, dict) else {"obs": obs_rms}
            for key, rms in stats.items():
                self.register_buffer(f"obs_mean_{key}", th.as_tensor(rms.mean, dtype=th.float64))
                self.register_buffer(f"obs_std_{key}", th.as_tensor(np.sqrt(rms.var + vec_normalize.epsilon), dtype=th.float64))
                self.normalized_keys.append(key)
            self.clip_obs = float(vec_normalize.clip_obs)
        # MaskedVecNormalize's table of optional rows (empty rows zeros, the mask kept 0 / 1): (start, count, size)
        self.masked_rows: tuple[int, int, int] | None = None
        # (getattr on a VecNormalize without its environment would recurse in VecEnvWrapper.__getattr__)
        if self.normalized_keys == ["obs"] and isinstance(vec_normalize, MaskedVecNormalize):
            start, count, size = vec_normalize.rows
            self.masked_rows = (int(start), int(count), int(size))

    @property
    def default_noise_shape(self) -> tuple[int, ...]:
        """Shape of the noise input's default value (zeros): a batch of 1, broadcast over the observations."""
        return (1, *self.actor.noise_shape)

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
        """
        What ``actor.sample(features, noise)`` computes, up to float rounding, written for a small traced graph.

        :param features: State features ``(batch, features_dim)``
        :param noise: ``(batch or 1, *actor.noise_shape)``; ``None`` for zeros (the deterministic action)
        :return: Actions in [-1, 1] (before the final clipping)
        """

    def forward(self, obs: PyTorchObs, noise: th.Tensor | None = None) -> th.Tensor:
        """
        :param obs: Raw observations ``(batch, *obs_shape)``, or a dict of them for a Dict observation space
        :param noise: The generator's noise ``(batch, *actor.noise_shape)``, or with a batch of 1 for all the batch;
            ``None`` for 0, the deterministic action
        :return: Actions in the environment's units ``(batch, action_dim)``
        """
        if isinstance(obs, dict):
            obs = {key: self._normalize(value, key) if key in self.normalized_keys else value for key, value in obs.items()}
        elif self.normalized_keys:
            obs = self._normalize(obs, "obs")
        features = self.actor.extract_features(obs, self.actor.features_extractor)
        actions = self.generate(features, noise)
        return th.addcmul(self.action_center, self.action_half_range, actions.clamp(-1.0, 1.0))


class ExportableFlowPolicy(ExportablePolicy):
    """
    The deployment graph of a DACER-F actor: the ``n_sampling_steps`` Euler steps of ``FlowActor.sample`` from
    ``a0``, unrolled, with the velocity network's first layer split by input for a smaller graph.

    :param actor: The flow actor (``model.actor``)
    :param n_sampling_steps: Number of Euler steps, fixed in the graph (the actor's ``n_sampling_steps`` by default)
    :param vec_normalize: VecNormalize wrapper the model was trained with (see :class:`ExportablePolicy`)
    """

    noise_name = "a0"

    actor: FlowActor
    # Buffers (registered in __init__)
    state_weight: th.Tensor
    action_weight: th.Tensor
    time_weight: th.Tensor
    first_bias: th.Tensor

    def __init__(self, actor: FlowActor, n_sampling_steps: int | None = None, vec_normalize: VecNormalize | None = None):
        super().__init__(actor, vec_normalize)
        self.n_sampling_steps = actor.n_sampling_steps if n_sampling_steps is None else n_sampling_steps
        if isinstance(self.n_sampling_steps, bool) or not isinstance(self.n_sampling_steps, int) or self.n_sampling_steps < 1:
            raise ValueError(f"n_sampling_steps must be an integer >= 1, got {self.n_sampling_steps!r}")
        step = 1.0 / self.n_sampling_steps
        # Euler steps a <- a + v / N: the last layer is scaled by 1 / N so that the network outputs the step itself
        last_layer = _linear(self.actor.network[-1])
        last_layer.weight.mul_(step)
        last_layer.bias.mul_(step)
        # The first layer, split by input ([features, actions, time]): the state term is one Gemm, the time term a
        # constant, and a (1, action_dim) a0 broadcasts over the batch; without a0 (= 0) the action term is left out
        first_layer = _linear(self.actor.network[0])
        state_weight, action_weight, time_weight = first_layer.weight.split(
            [self.actor.features_dim, self.actor.action_dim, 1], 1
        )
        self.register_buffer("state_weight", state_weight.t().contiguous())
        self.register_buffer("action_weight", action_weight.contiguous())
        self.register_buffer("time_weight", time_weight[:, 0].contiguous())
        self.register_buffer("first_bias", first_layer.bias.clone())
        self.velocity_tail = self.actor.network[1:]

    def generate(self, features: th.Tensor, noise: th.Tensor | None) -> th.Tensor:
        # The Euler steps of FlowActor.sample from t = 0, unrolled (their number is fixed in the graph)
        actions = noise
        for k in range(self.n_sampling_steps):
            bias = self.first_bias if k == 0 else self.first_bias + (k / self.n_sampling_steps) * self.time_weight
            if actions is not None:
                bias = nn.functional.linear(actions, self.action_weight, bias)
            euler_step = self.velocity_tail(th.addmm(bias, features, self.state_weight))
            actions = euler_step if actions is None else actions + euler_step
        assert actions is not None  # n_sampling_steps >= 1
        return actions


class ExportableDiffusionPolicy(ExportablePolicy):
    """
    The deployment graph of a DACER actor: the ``n_diffusion_steps`` reverse steps of ``DiffusionActor.sample``,
    unrolled, with the time embeddings computed once (constants of the graph) and the noise-prediction network's
    first layer split by input. The number of steps is that of the noise schedule the model was trained with.

    :param actor: The diffusion actor (``model.actor``)
    :param vec_normalize: VecNormalize wrapper the model was trained with (see :class:`ExportablePolicy`)
    """

    noise_name = "noise"

    actor: DiffusionActor
    # Buffers (registered in __init__)
    state_weight: th.Tensor
    action_weight: th.Tensor
    time_terms: th.Tensor

    def __init__(self, actor: DiffusionActor, vec_normalize: VecNormalize | None = None):
        super().__init__(actor, vec_normalize)
        self.reverse_coefficients = list(self.actor.reverse_coefficients)
        first_layer = _linear(self.actor.network[0])
        state_weight, action_weight, time_weight = first_layer.weight.split(
            [self.actor.features_dim, self.actor.action_dim, self.actor.time_embedding_dim], 1
        )
        self.register_buffer("state_weight", state_weight.t().contiguous())
        self.register_buffer("action_weight", action_weight.contiguous())
        with th.no_grad():
            # The time term of the first layer at each step t, with its bias: (n_diffusion_steps, hidden)
            time_terms = nn.functional.linear(self.actor.time_embeddings(), time_weight, first_layer.bias)
        self.register_buffer("time_terms", time_terms.contiguous())
        self.noise_tail = self.actor.network[1:]

    def generate(self, features: th.Tensor, noise: th.Tensor | None) -> th.Tensor:
        # The reverse steps of DiffusionActor.sample from t = T - 1 down to 0, unrolled; without noise, x_T = 0 and
        # the terms of the (zero) action and posterior noise are left out
        state_term = features @ self.state_weight
        actions = None if noise is None else noise[:, 0]  # x_T = noise[:, 0], as in DiffusionActor.sample
        for t in reversed(range(len(self.reverse_coefficients))):
            c0, c1, m0, m1, std = self.reverse_coefficients[t]
            hidden = state_term + self.time_terms[t]
            if actions is not None:
                hidden = hidden + nn.functional.linear(actions, self.action_weight)
            predicted_noise = self.noise_tail(hidden)
            if actions is None:
                actions = m0 * (-c1 * predicted_noise).clamp(-1.0, 1.0)
            else:
                actions = m0 * (c0 * actions - c1 * predicted_noise).clamp(-1.0, 1.0) + m1 * actions
            if noise is not None and t > 0:
                actions = actions + std * noise[:, t]
        assert actions is not None  # n_diffusion_steps >= 1
        return actions


class ExportableGaussianPolicy(ExportablePolicy):
    """
    The deployment graph of a DSAC actor: ``tanh(μ)`` (no noise) or ``tanh(μ + σ ξ)`` (noise ``ξ``), ``μ`` and the
    clipped ``log σ`` from one call of the actor's network, as ``GaussianActor.sample``.

    :param actor: The tanh-Gaussian actor (``model.actor``)
    :param vec_normalize: VecNormalize wrapper the model was trained with (see :class:`ExportablePolicy`)
    """

    noise_name = "noise"

    actor: GaussianActor

    def __init__(self, actor: GaussianActor, vec_normalize: VecNormalize | None = None):
        super().__init__(actor, vec_normalize)
        self.log_std_min, self.log_std_max = actor.log_std_min, actor.log_std_max

    def generate(self, features: th.Tensor, noise: th.Tensor | None) -> th.Tensor:
        mean, log_std = self.actor.network(features).chunk(2, dim=-1)
        if noise is None:
            return th.tanh(mean)
        return th.tanh(mean + log_std.clamp(self.log_std_min, self.log_std_max).exp() * noise)


class FlaggedPolicy(nn.Module):
    """
    The ONNX graph of an :class:`ExportablePolicy`, which cannot raise: ``(action, finite)``, ``finite[i]`` false
    (and ``action[i]`` NaN) where observation ``i`` has a NaN or infinite entry, so that no finite-looking action is
    computed from it.
    """

    def __init__(self, policy: ExportablePolicy):
        super().__init__()
        self.policy = policy

    def forward(self, obs: PyTorchObs, noise: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        # obs * 0 is 0 for a finite entry and NaN for a NaN or infinite one, so each row's sum is 0 or NaN: added to
        # the action it makes the row NaN, compared with 0 it is the flag (fewer graph nodes than IsInf / IsNaN / Where)
        values = list(obs.values()) if isinstance(obs, dict) else [obs]
        # Integer observations (images, discrete) are always finite
        poison = [
            (value * 0).reshape(value.shape[0], -1).sum(dim=1, keepdim=True) for value in values if value.is_floating_point()
        ]
        actions = self.policy(obs, noise)
        if not poison:
            return actions, th.ones(actions.shape[0], dtype=th.bool, device=actions.device)
        total = poison[0] if len(poison) == 1 else th.cat(poison, dim=1).sum(dim=1, keepdim=True)
        return actions + total.to(actions.dtype), total[:, 0] == 0


def _linear(layer: nn.Module) -> nn.Linear:
    """``layer``, the first or last layer of an actor's network, as the ``nn.Linear`` the graph splits or scales."""
    if not isinstance(layer, nn.Linear):
        raise TypeError(f"The actor's network must start and end with nn.Linear layers, got a {type(layer).__name__}")
    return layer


def exportable_policy(
    actor: GenerativeActor | GaussianActor, n_sampling_steps: int | None = None, vec_normalize: VecNormalize | None = None
) -> ExportablePolicy:
    """
    The deployment graph of an actor of this package.

    :param actor: ``model.actor`` of a DACERF, DACER or DSAC model
    :param n_sampling_steps: DACERF: number of Euler steps fixed in the graph (the actor's by default). DACER: leave it
        out (or give the model's ``n_diffusion_steps``): the number of reverse steps is fixed by the noise schedule.
        DSAC: leave it out (one network call)
    :param vec_normalize: VecNormalize wrapper the model was trained with, if any
    :raises TypeError: for another actor
    :raises ValueError: for a DACER ``n_sampling_steps`` other than its ``n_diffusion_steps``, or any for DSAC
    """
    if isinstance(actor, GaussianActor):
        if n_sampling_steps is not None:
            raise ValueError(
                f"n_sampling_steps={n_sampling_steps!r}: a DSAC policy computes its action in one network call; leave "
                "n_sampling_steps out (a DACERF option)."
            )
        return ExportableGaussianPolicy(actor, vec_normalize)
    if isinstance(actor, FlowActor):
        return ExportableFlowPolicy(actor, n_sampling_steps, vec_normalize)
    if isinstance(actor, DiffusionActor):
        if n_sampling_steps is not None and n_sampling_steps != actor.n_diffusion_steps:
            raise ValueError(
                f"n_sampling_steps={n_sampling_steps!r}: a DACER policy runs the {actor.n_diffusion_steps} reverse steps "
                "of the noise schedule it was trained with; leave n_sampling_steps out (a DACERF option)."
            )
        return ExportableDiffusionPolicy(actor, vec_normalize)
    raise TypeError(
        f"export_policy exports DACERF, DACER and DSAC models (a sb3_dacerf FlowActor, DiffusionActor or GaussianActor), "
        f"got an actor of type {type(actor).__name__}. "
        "For SB3's own algorithms see https://stable-baselines3.readthedocs.io/en/master/guide/export.html"
    )


def _mean_shape(obs_rms: object) -> tuple[int, ...]:
    """Shape of the mean of VecNormalize statistics, ``()`` when they have none."""
    mean = getattr(obs_rms, "mean", None)
    return () if mean is None else np.shape(mean)


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
                f"{_mean_shape(obs_rms)} but the model takes Dict observations with keys "
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
    if _mean_shape(obs_rms) != observation_space.shape:
        raise ValueError(
            f"The VecNormalize statistics normalise observations of shape {_mean_shape(obs_rms)} "
            f"but the model's observations have shape {observation_space.shape}. {advice}"
        )
