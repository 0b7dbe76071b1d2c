"""
Twin (or more) critics evaluated in one pass: ensemble layers whose weights hold every critic, stacked on a first
dimension, so that each layer of all the critics is one batched matrix product.

The critics keep SB3's ``ContinuousCritic`` interface (``critic(obs, actions)`` returns one ``(batch, 1)`` tensor
per critic, ``n_critics`` critics) and its numbers: each member is initialised as SB3 initialises one critic network
(the same random draws, in the same order, as the separate networks of earlier versions), and models saved with
separate networks (keys ``qf<j>.<k>.*`` or ``q_networks.<j>.<k>.*``) load into the ensemble.
"""

import math
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, create_mlp
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn
from torch.nn import functional as F

from sb3_dacerf.common.utils import is_batch_renorm


class EnsembleLinear(nn.Module):
    """
    ``n_members`` linear layers applied in one batched product: ``y[j] = x[j] @ weight[j] + bias[j]``.

    :param n_members: Number of members (critics)
    :param in_features: Size of each input sample
    :param out_features: Size of each output sample
    """

    def __init__(self, n_members: int, in_features: int, out_features: int):
        super().__init__()
        self._allocate(n_members, in_features, out_features)
        self.reset_parameters()

    def _allocate(self, n_members: int, in_features: int, out_features: int) -> None:
        self.n_members, self.in_features, self.out_features = n_members, in_features, out_features
        #: ``(n_members, in_features, out_features)``: member ``j`` computes ``x @ weight[j]``
        self.weight = nn.Parameter(th.empty(n_members, in_features, out_features))
        #: ``(n_members, out_features)``
        self.bias = nn.Parameter(th.empty(n_members, out_features))

    def reset_parameters(self) -> None:
        """Initialise each member as ``nn.Linear(in_features, out_features)`` does (the same random draws)."""
        bound = 1 / math.sqrt(self.in_features) if self.in_features > 0 else 0.0
        with th.no_grad():
            for member in range(self.n_members):
                weight = th.empty(self.out_features, self.in_features)
                nn.init.kaiming_uniform_(weight, a=math.sqrt(5))
                self.weight[member].copy_(weight.t())
                nn.init.uniform_(self.bias[member], -bound, bound)

    @classmethod
    def from_members(cls, linears: list[nn.Linear]) -> "EnsembleLinear":
        """An ensemble holding copies of the weights of ``linears`` (with biases, all of one shape)."""
        first = linears[0]
        ensemble = cls.__new__(cls)  # without the random initialisation, which the copies below would overwrite
        nn.Module.__init__(ensemble)
        ensemble._allocate(len(linears), first.in_features, first.out_features)
        with th.no_grad():
            ensemble.weight.copy_(th.stack([linear.weight.t() for linear in linears]))
            ensemble.bias.copy_(th.stack([_bias(linear) for linear in linears]))
        return ensemble

    def forward(self, x: th.Tensor) -> th.Tensor:
        """
        :param x: ``(batch, in_features)``, the same input for every member, or ``(n_members, batch, in_features)``
        :return: ``(n_members, batch, out_features)``
        """
        if x.dim() == 2:
            x = x.expand(self.n_members, *x.shape)
        return th.baddbmm(self.bias.unsqueeze(1), x, self.weight)

    def extra_repr(self) -> str:
        return f"n_members={self.n_members}, in_features={self.in_features}, out_features={self.out_features}"


class EnsembleLayerNorm(nn.Module):
    """
    ``LayerNorm`` over the last dimension with an affine transform of its own for each member.

    :param n_members: Number of members (critics)
    :param num_features: Size of the normalised dimension
    :param eps: Added to the variance, as in ``nn.LayerNorm``
    """

    def __init__(self, n_members: int, num_features: int, eps: float = 1e-5):
        super().__init__()
        self.n_members, self.num_features, self.eps = n_members, num_features, eps
        self.weight = nn.Parameter(th.ones(n_members, num_features))
        self.bias = nn.Parameter(th.zeros(n_members, num_features))

    @classmethod
    def from_members(cls, norms: list[nn.LayerNorm]) -> "EnsembleLayerNorm":
        """An ensemble holding copies of the affine parameters of ``norms`` (1-d, elementwise affine)."""
        first = norms[0]
        ensemble = cls(len(norms), first.normalized_shape[0], first.eps)
        with th.no_grad():
            ensemble.weight.copy_(th.stack([norm.weight for norm in norms]))
            ensemble.bias.copy_(th.stack([norm.bias for norm in norms]))
        return ensemble

    def forward(self, x: th.Tensor) -> th.Tensor:
        """:param x: ``(n_members, batch, num_features)``"""
        normalised = F.layer_norm(x, (self.num_features,), eps=self.eps)
        return th.addcmul(self.bias.unsqueeze(1), normalised, self.weight.unsqueeze(1))

    def extra_repr(self) -> str:
        return f"n_members={self.n_members}, num_features={self.num_features}, eps={self.eps}"


class EnsembleBatchRenorm(nn.Module):
    """
    Batch renormalisation (Ioffe 2017) with running statistics and an affine transform of its own for each member:
    the computation of sb3-contrib's ``BatchRenorm1d`` (CrossQ's), member by member. In training mode it normalises
    with the batch's statistics (corrected towards the running ones after ``warmup_steps`` steps) and updates the
    running statistics; in evaluation mode it normalises with the running statistics.

    :param n_members: Number of members (critics)
    :param num_features: Number of features
    :param eps: Added to the variance
    :param momentum: Rate of the running averages
    :param warmup_steps: Steps of plain batch normalisation before the renormalisation
    """

    def __init__(
        self, n_members: int, num_features: int, eps: float = 0.001, momentum: float = 0.01, warmup_steps: int = 100_000
    ):
        super().__init__()
        self.n_members, self.num_features = n_members, num_features
        self.eps, self.momentum, self.warmup_steps = eps, momentum, warmup_steps
        # Clipping of the renormalisation's correction (r, d), as in sb3-contrib
        self.rmax, self.dmax = 3.0, 5.0
        self.register_buffer("ra_mean", th.zeros(n_members, num_features))
        self.register_buffer("ra_var", th.ones(n_members, num_features))
        self.register_buffer("steps", th.tensor(0, dtype=th.long))
        self.scale = nn.Parameter(th.ones(n_members, num_features))
        self.bias = nn.Parameter(th.zeros(n_members, num_features))

    ra_mean: th.Tensor
    ra_var: th.Tensor
    steps: th.Tensor

    @classmethod
    def from_members(cls, layers: list[Any]) -> "EnsembleBatchRenorm":
        """An ensemble holding copies of the parameters and statistics of sb3-contrib ``BatchRenorm1d`` layers."""
        first = layers[0]
        if not all(layer.affine for layer in layers):
            raise ValueError("EnsembleBatchRenorm holds affine batch renormalisations only (BatchRenorm1d(affine=True))")
        ensemble = cls(len(layers), first.num_features, first.eps, first.momentum, first.warmup_steps)
        with th.no_grad():
            for name in ("scale", "bias", "ra_mean", "ra_var"):
                getattr(ensemble, name).copy_(th.stack([getattr(layer, name) for layer in layers]))
            ensemble.steps.copy_(first.steps)
        return ensemble

    def normalisation(self) -> tuple[th.Tensor, th.Tensor]:
        """The affine map of evaluation mode, ``x -> gain * x + shift``: ``gain``, ``shift``, ``(n_members, num_features)``."""
        gain = self.scale / (self.ra_var + self.eps).sqrt()
        return gain, self.bias - gain * self.ra_mean

    def forward(self, x: th.Tensor) -> th.Tensor:
        """
        :param x: ``(batch, num_features)`` (the same input for every member) or ``(n_members, batch, num_features)``
        :return: ``(n_members, batch, num_features)``
        """
        if self.training:
            batch_mean = x.mean(dim=-2)
            batch_var = x.var(dim=-2)
            if self.steps > self.warmup_steps:
                running_std = (self.ra_var + self.eps).sqrt()
                r = ((batch_var + self.eps).sqrt() / running_std).detach().clamp(1 / self.rmax, self.rmax)
                d = ((batch_mean - self.ra_mean) / running_std).detach().clamp(-self.dmax, self.dmax)
                mean, var = batch_mean - d * batch_var.sqrt() / r, batch_var / r**2
            else:
                mean, var = batch_mean, batch_var
            self.ra_mean += self.momentum * (batch_mean.detach() - self.ra_mean)
            self.ra_var += self.momentum * (batch_var.detach() - self.ra_var)
            self.steps += 1
        else:
            mean, var = self.ra_mean, self.ra_var
        mean = mean.expand(self.n_members, self.num_features).unsqueeze(1)
        var = var.expand(self.n_members, self.num_features).unsqueeze(1)
        normalised = (x - mean) / (var + self.eps).sqrt()
        return self.scale.unsqueeze(1) * normalised + self.bias.unsqueeze(1)

    def extra_repr(self) -> str:
        return (
            f"n_members={self.n_members}, num_features={self.num_features}, momentum={self.momentum}, "
            f"warmup_steps={self.warmup_steps}"
        )


def ensemble_of(modules: list[nn.Module]) -> nn.Module:
    """
    The ensemble layer of the same layer of each member network: :class:`EnsembleLinear` of ``nn.Linear``,
    :class:`EnsembleLayerNorm` of ``nn.LayerNorm``, :class:`EnsembleBatchRenorm` of sb3-contrib's ``BatchRenorm1d``,
    the first module itself for parameter-free modules (activations), which act elementwise on any shape.
    """
    first = modules[0]
    if type(first) is nn.Linear:
        return EnsembleLinear.from_members(modules)  # type: ignore[arg-type]
    if type(first) is nn.LayerNorm:
        return EnsembleLayerNorm.from_members(modules)  # type: ignore[arg-type]
    if is_batch_renorm(first):
        return EnsembleBatchRenorm.from_members(modules)
    if any(True for _ in first.parameters()) or any(True for _ in first.buffers()):
        raise ValueError(
            f"No ensemble version of {type(first).__name__}: critics are built of Linear, LayerNorm, BatchRenorm1d "
            "and activations"
        )
    return first


class EnsembleCritic(BaseModel):
    """
    ``n_critics`` Q-networks ``Q_j(s, a) = MLP_j(concat(features(s), a))`` run as one ensemble network
    (:attr:`ensemble`: :class:`EnsembleLinear` layers with activations between them, normalisation layers in the
    subclasses). Same arguments and interface as SB3's ``ContinuousCritic``: calling it returns one ``(batch, 1)``
    tensor per critic; :meth:`q_values` returns them stacked.

    :param observation_space: Observation space
    :param action_space: Action space
    :param net_arch: Hidden layer sizes of each Q-network
    :param features_extractor: Network to extract features (a CNN when using images, a nn.Flatten() layer otherwise)
    :param features_dim: Number of features
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not, dividing by 255.0 (True by default)
    :param n_critics: Number of critic networks to create.
    :param share_features_extractor: Whether the features extractor is shared with the actor (it then gets no
        gradient from the critic)
    """

    features_extractor: BaseFeaturesExtractor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        n_critics: int = 2,
        share_features_extractor: bool = True,
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        self.share_features_extractor = share_features_extractor
        self.n_critics = n_critics
        input_dim = features_dim + get_action_dim(action_space)
        normalisation = self.normalisation_modules()
        if normalisation:
            # The plain networks that SB3's ContinuousCritic draws before the normalised ones replaced them in earlier
            # versions: drawn and dropped, so that a seed gives the initial weights it gave then
            for _ in range(n_critics):
                create_mlp(input_dim, 1, net_arch, activation_fn)
        members = [nn.Sequential(*create_mlp(input_dim, 1, net_arch, activation_fn, **normalisation)) for _ in range(n_critics)]
        self.ensemble = nn.Sequential(*[ensemble_of(list(layers)) for layers in zip(*members, strict=True)])

    @classmethod
    def normalisation_modules(cls) -> dict[str, Any]:
        """``pre_linear_modules`` and/or ``post_linear_modules`` of ``create_mlp`` for each member (none here)."""
        return {}

    def critic_features(self, obs: PyTorchObs) -> th.Tensor:
        """The features of ``obs`` (without gradient to a features extractor shared with the actor)."""
        with th.set_grad_enabled(not self.share_features_extractor):
            return self.extract_features(obs, self.features_extractor)

    def q_values_of_features(self, features: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """
        :param features: State features ``(batch, features_dim)``
        :param actions: Actions ``(batch, action_dim)``
        :return: Every critic's ``Q_j(s, a)``, ``(n_critics, batch, 1)``
        """
        return self.ensemble(th.cat([features, actions], dim=1))

    def q_values(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """Every critic's ``Q_j(s, a)``, ``(n_critics, batch, 1)``."""
        return self.q_values_of_features(self.critic_features(obs), actions)

    def forward(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        """One ``(batch, 1)`` tensor per critic, as SB3's ``ContinuousCritic``."""
        return tuple(self.q_values(obs, actions).unbind(0))

    def q1_forward(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """The first critic's ``Q_1(s, a)``, ``(batch, 1)``, as SB3's ``ContinuousCritic.q1_forward``."""
        return self.q_values(obs, actions)[0]

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        convert_separate_critics(state_dict, prefix, self)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


#: The names under which earlier versions saved the layer ``<k>`` of critic ``<j>``: ``<name><j>.<k>.<parameter>``
SEPARATE_CRITIC_PREFIXES = ("q_networks.", "qf")


def convert_separate_critics(state_dict: dict[str, Any], prefix: str, critic: EnsembleCritic) -> None:
    """
    Rewrite, in place, the entries of separate critic networks saved by earlier versions (``qf<j>.<k>.*``, and
    ``q_networks.<j>.<k>.*`` which repeat them) as those of ``critic``'s ensemble (``ensemble.<k>.*``), stacked over
    the critics; a state dict without them is left as it is. Layers missing from ``state_dict`` stay missing.

    :param state_dict: A module state dict (as given to ``_load_from_state_dict``)
    :param prefix: The critic's prefix in it (e.g. ``"critic."``)
    :param critic: The critic it is loaded into
    """
    separate = {
        key: key[len(prefix) :]
        for key in state_dict
        if key.startswith(prefix) and key[len(prefix) :].startswith(SEPARATE_CRITIC_PREFIXES)
    }
    if not separate:
        return
    members: dict[tuple[int, int, str], Any] = {}
    for key, name in separate.items():
        value = state_dict.pop(key)
        head, layer, entry = name.rsplit(".", 2) if name.startswith("qf") else name[len("q_networks.") :].split(".", 2)
        member = int(head[len("qf") :]) if name.startswith("qf") else int(head)
        members.setdefault((member, int(layer), entry), value)
    for index, module in enumerate(critic.ensemble):
        for entry in [name for name, _ in module.named_parameters()] + [name for name, _ in module.named_buffers()]:
            if any((member, index, entry) not in members for member in range(critic.n_critics)):
                continue
            values: list[th.Tensor] = [members[(member, index, entry)] for member in range(critic.n_critics)]
            if isinstance(module, EnsembleLinear) and entry == "weight":
                stacked = th.stack([value.t() for value in values])
            elif entry == "steps":  # the same count in every member
                stacked = values[0]
            else:
                stacked = th.stack(values)
            state_dict[f"{prefix}ensemble.{index}.{entry}"] = stacked


def convert_separate_critics_optimizer(optimizer_state: dict[str, Any], critic: EnsembleCritic, n_leading: int) -> dict[str, Any]:
    """
    The state of a critic optimizer saved by an earlier version, whose parameters were the separate networks' (critic
    after critic, layer after layer), for the optimizer of ``critic``'s ensemble: each state entry stacked over the
    critics as the parameters are (weights transposed), scalar entries (Adam's ``step``) taken from the first critic.

    :param optimizer_state: ``optimizer.state_dict()`` of the earlier version (one parameter group)
    :param critic: The ensemble critic whose optimizer will load the result
    :param n_leading: Parameters before the critic networks in the group (those of an unshared features extractor)
    :return: The converted state dict (``optimizer_state`` is not modified)
    """
    ensemble_parameters = [
        (index, name, param) for index, module in enumerate(critic.ensemble) for name, param in module.named_parameters()
    ]
    per_member = len(ensemble_parameters)
    (group,) = optimizer_state["param_groups"]
    old_ids = group["params"]
    if len(old_ids) != n_leading + critic.n_critics * per_member:
        raise ValueError(
            f"Cannot convert the saved critic optimizer: it has {len(old_ids)} parameters, not the "
            f"{n_leading + critic.n_critics * per_member} of {critic.n_critics} separate critics of this architecture"
        )
    state = optimizer_state["state"]
    new_state: dict[int, Any] = {}
    for position in range(n_leading):
        if old_ids[position] in state:
            new_state[position] = state[old_ids[position]]
    for offset, (_, name, param) in enumerate(ensemble_parameters):
        entries = [state.get(old_ids[n_leading + member * per_member + offset]) for member in range(critic.n_critics)]
        if any(entry is None for entry in entries):
            continue
        converted = {}
        for key, value in entries[0].items():
            if isinstance(value, th.Tensor) and value.dim() > 0:
                values = [entry[key] for entry in entries]
                stacked = th.stack([v.t() if name == "weight" and v.dim() == 2 else v for v in values])
                converted[key] = stacked.reshape(param.shape)
            else:
                converted[key] = value
        new_state[n_leading + offset] = converted
    new_group = {**group, "params": list(range(n_leading + per_member))}
    return {"state": new_state, "param_groups": [new_group]}


class LayerNormCritic(EnsembleCritic):
    """
    Ensemble critics with ``LayerNorm`` after every hidden linear layer (before the activation), as in the critics
    of BRO, SimBa and FlowRL: normalised features keep the Q-values and ``∇_a Q`` (which drives the Langevin
    targets) on a stable scale. Same arguments as :class:`EnsembleCritic`.
    """

    @classmethod
    def normalisation_modules(cls) -> dict[str, Any]:
        return dict(post_linear_modules=[nn.LayerNorm])


class BatchRenormCritic(EnsembleCritic):
    """
    Ensemble critics with CrossQ's batch renormalisation (sb3-contrib's ``BatchRenorm1d`` computation, momentum
    0.01) before every linear layer. The layers normalise with the running statistics except while
    :meth:`set_bn_training_mode` has them in training mode: the algorithm turns that on only for the critic update's
    joint forward pass over ``(s, a)`` and ``(s', a')``. Same arguments as :class:`EnsembleCritic`.
    """

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.set_bn_training_mode(False)

    @classmethod
    def normalisation_modules(cls) -> dict[str, Any]:
        try:
            from sb3_contrib.common.torch_layers import BatchRenorm1d
        except ImportError as error:
            raise ImportError("critic='batch_renorm' uses sb3-contrib's BatchRenorm1d: pip install 'sb3-contrib>=2.4'") from error
        return dict(pre_linear_modules=[BatchRenorm1d])

    def set_training_mode(self, mode: bool) -> None:
        super().set_training_mode(mode)
        # The normalisation layers leave running-statistics mode only through set_bn_training_mode
        self.set_bn_training_mode(False)

    def set_bn_training_mode(self, mode: bool) -> None:
        """
        :param mode: Normalise with the batch's statistics and update the running ones (``True``), or normalise with
            the running statistics (``False``)
        """
        for module in self.modules():
            if isinstance(module, EnsembleBatchRenorm):
                module.train(mode)


def _bias(linear: nn.Linear) -> th.Tensor:
    if linear.bias is None:
        raise ValueError("EnsembleLinear holds linear layers with a bias only")
    return linear.bias
