from collections.abc import Callable
from typing import Any

import torch as th
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, NatureCNN, create_mlp
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn

from sb3_dacerf.common.policies import (
    EnsembleBatchRenorm,
    EnsembleCritic,
    EnsembleLayerNorm,
    EnsembleLinear,
    GenerativeActor,
    TwinCriticPolicy,
)


class FlowActor(GenerativeActor):
    """
    Flow-matching actor of DACER-F: a velocity field ``v_θ(s, a_t, t)`` (:attr:`network`) whose Euler sampler
    integrates ``da/dt = v_θ(s, a, t)`` from ``a_0`` (``0`` if deterministic) at ``t = 0`` to ``t = 1``, then clips
    to [-1, 1]. Takes the arguments of :class:`~sb3_dacerf.common.policies.GenerativeActor`, and:

    :param n_sampling_steps: Number of Euler steps from noise to action
    """

    own_arguments = ("n_sampling_steps",)

    def __init__(self, *args: Any, n_sampling_steps: int = 1, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.n_sampling_steps = n_sampling_steps
        with th.no_grad():
            self.log_alpha.fill_(float("-inf"))
        # Input: state features, the point a_t on the path, and the time t
        self.network = nn.Sequential(
            *create_mlp(self.features_dim + self.action_dim + 1, self.action_dim, self.net_arch, self.activation_fn)
        )

    @property
    def noise_shape(self) -> tuple[int, ...]:
        """``(action_dim,)``: the flow's starting point ``a_0``."""
        return (self.action_dim,)

    def velocity(self, features: th.Tensor, actions: th.Tensor, time: th.Tensor) -> th.Tensor:
        """The velocity ``v_θ(s, a_t, t)`` at state features ``(batch, features_dim)``, points ``a_t`` on the path
        ``(batch, action_dim)`` and times ``t`` in [0, 1] ``(batch, 1)``."""
        return self.network(th.cat([features, actions, time], dim=1))

    def sample(self, features: th.Tensor, noise: th.Tensor | None = None) -> th.Tensor:
        """Integrate the flow from ``noise`` ``a_0`` (``None``: zeros) with ``n_sampling_steps`` Euler steps at
        ``t = k / N``, then :meth:`squash`."""
        if noise is None:
            noise = th.zeros((features.shape[0], self.action_dim), device=features.device, dtype=features.dtype)
        actions = noise
        step = 1.0 / self.n_sampling_steps
        for k in range(self.n_sampling_steps):
            time = th.full((noise.shape[0], 1), k * step, device=noise.device, dtype=noise.dtype)
            actions = actions + step * self.velocity(features, actions, time)
        return self.squash(actions)

    def squash(self, actions: th.Tensor) -> th.Tensor:
        """The flow's end points ``(batch, action_dim)`` clamped to [-1, 1] (zero gradient in saturated coordinates)."""
        return actions.clamp(-1.0, 1.0)


# Backward pass of each supported activation: dQ/dz from dQ/dh, h = activation(z) (the kernels autograd uses)
ACTIVATION_BACKWARDS: dict[type[nn.Module], Callable[[nn.Module, th.Tensor, th.Tensor], th.Tensor]] = {
    nn.ReLU: lambda module, grad, z: th.ops.aten.threshold_backward(grad, z, 0.0),
    nn.LeakyReLU: lambda module, grad, z: th.ops.aten.leaky_relu_backward(grad, z, module.negative_slope, False),
    nn.Tanh: lambda module, grad, z: th.ops.aten.tanh_backward(grad, th.tanh(z)),
    nn.ELU: lambda module, grad, z: th.ops.aten.elu_backward(grad, module.alpha, 1.0, 1.0, False, z),
    nn.SiLU: lambda module, grad, z: th.ops.aten.silu_backward(grad, z),
    nn.Mish: lambda module, grad, z: th.ops.aten.mish_backward(grad, z),
    nn.GELU: lambda module, grad, z: th.ops.aten.gelu_backward(grad, z, approximate=module.approximate),
}


class DACERFPolicy(TwinCriticPolicy):
    """
    Policy class (flow actor and twin critics) for DACER-F. Takes the arguments of
    :class:`~sb3_dacerf.common.policies.TwinCriticPolicy`, ``activation_fn`` one of :data:`ACTIVATION_BACKWARDS`, and:

    :param n_sampling_steps: Number of Euler steps of the flow sampler
    :param distributional_critic: Gaussian critics ``N(Q_j, σ_j²)`` trained with DSAC-T's loss (two critics with
        target networks); ``Q_j`` is their mean
    """

    actor_class = FlowActor
    actor: FlowActor
    critic: EnsembleCritic
    critic_target: EnsembleCritic

    def __init__(self, *args: Any, n_sampling_steps: int = 1, distributional_critic: bool = False, **kwargs: Any):
        activation_fn = kwargs.get("activation_fn") or self.default_activation_fn
        if activation_fn not in ACTIVATION_BACKWARDS:
            raise ValueError(
                f"DACERF's critics take activation_fn={', '.join(cls.__name__ for cls in ACTIVATION_BACKWARDS)} (the "
                f"Langevin gradient is written out for them), not {activation_fn!r}."
            )
        if distributional_critic and kwargs.get("critic") == "batch_renorm":
            raise ValueError(
                "distributional_critic=True takes critics with target networks (DSAC-T's targets), not "
                "critic='batch_renorm': choose critic='layer_norm' or 'mlp', or distributional_critic=False."
            )
        if distributional_critic and kwargs.get("n_critics", 2) != 2:
            raise ValueError(
                f"distributional_critic=True takes exactly two critics (DSAC-T's target takes the smaller of two "
                f"means with its sample): n_critics={kwargs['n_critics']!r} must be 2, or distributional_critic=False."
            )
        self.distributional_critic = distributional_critic
        super().__init__(*args, actor_kwargs=dict(n_sampling_steps=n_sampling_steps), **kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "distributional_critic": self.distributional_critic}

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> EnsembleCritic:
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        critic_class = self.critic_classes[self.critic_kind]
        return critic_class(**critic_kwargs, distributional=self.distributional_critic).to(self.device)


# A hidden block of a written-out critic: (weight (n, in, out), bias (n, out), LayerNorm or None, activation)
_Block = tuple[th.Tensor, th.Tensor, EnsembleLayerNorm | None, nn.Module]


class MinQActionGradient:
    """
    ``∇_a min_j Q_j(s, a)`` of the ensemble ``critic`` at the fixed states ``observations``: the gradient of DACER-F's
    Langevin steps, written out without an autograd graph (:func:`written_out_layers`). The features, and every
    critic's first-layer contribution of the state, are computed once; the chain rule goes back through the critic
    with the smallest Q only, per sample (as autograd routes the gradient through ``min``).
    """

    def __init__(self, critic: EnsembleCritic, observations: PyTorchObs):
        #: ``min_j Q_j(s, a)`` at the actions of the first call (the Langevin loop's start), ``(batch, 1)``, detached
        self.start_min_q: th.Tensor | None = None
        with th.no_grad():
            self.features = critic.extract_features(observations, critic.features_extractor)
        self.blocks, (self.output_weight, self.output_bias) = written_out_layers(critic)
        first_weight, first_bias = self.blocks[0][0], self.blocks[0][1]
        n_members, n_features = first_weight.shape[0], self.features.shape[1]
        with th.no_grad():
            # W [s; a] + b = (W_s s + b) + W_a a: the state part is the same at every Langevin step
            self.state_part = th.baddbmm(
                first_bias.unsqueeze(1), self.features.expand(n_members, *self.features.shape), first_weight[:, :n_features]
            )
        self.action_weight = first_weight[:, n_features:]

    def __call__(self, actions: th.Tensor) -> th.Tensor:
        with th.no_grad():
            q_values, saved = self._forward(actions)
            # Per sample, only the first critic with the smallest Q is differentiated (as autograd through th.min),
            # each critic's backward pass on its own samples
            min_q, smallest = q_values.min(dim=0)
            if self.start_min_q is None:
                self.start_min_q = min_q
            smallest = smallest.squeeze(1)
            gradient = th.empty_like(actions)
            for member in range(q_values.shape[0]):
                rows = (smallest == member).nonzero().squeeze(1)
                if rows.numel() > 0:
                    gradient.index_copy_(0, rows, self._member_backward(member, rows, saved))
            return gradient

    def _member_backward(self, member: int, rows: th.Tensor, saved: list[tuple[th.Tensor, Any]]) -> th.Tensor:
        """``∇_a Q_member`` at the samples ``rows``, from the forward pass's ``saved`` pre-activations."""
        gradient = self.output_weight[member].t().expand(rows.numel(), -1)
        for index in range(len(self.blocks) - 1, -1, -1):
            weight, _, norm, activation = self.blocks[index]
            z, norm_cache = saved[index]
            gradient = ACTIVATION_BACKWARDS[type(activation)](activation, gradient, z[member].index_select(0, rows))
            if norm is not None and norm_cache is not None:  # both or neither: dQ/dz of y = LayerNorm(z), autograd's kernel
                z_in, mean, inv_std = (tensor[member].index_select(0, rows) for tensor in norm_cache)
                gradient = th.ops.aten.native_layer_norm_backward(
                    gradient * norm.weight[member], z_in, (norm.num_features,), mean, inv_std, None, None, [True, False, False]
                )[0]
            gradient = gradient @ (self.action_weight if index == 0 else weight)[member].t()
        return gradient

    def min_q(self, actions: th.Tensor) -> th.Tensor:
        """``min_j Q_j(s, a)`` at the fixed states, ``(batch, 1)``, without gradient (one forward pass)."""
        with th.no_grad():
            return self._forward(actions)[0].min(dim=0).values

    def _forward(self, actions: th.Tensor) -> tuple[th.Tensor, list[tuple[th.Tensor, Any]]]:
        """Every critic's Q ``(n_critics, batch, 1)`` through the hidden blocks, and what the backward pass needs."""
        saved = []
        hidden = actions
        for index, (weight, bias, norm, activation) in enumerate(self.blocks):
            if index == 0:
                z = th.baddbmm(self.state_part, actions.expand(self.state_part.shape[0], *actions.shape), self.action_weight)
            else:
                z = th.baddbmm(bias.unsqueeze(1), hidden, weight)
            norm_cache = None
            if norm is not None:  # with autograd's kernel, keeping what its backward needs (input, mean, 1/σ)
                normalised, mean, inv_std = th.native_layer_norm(z, (norm.num_features,), None, None, norm.eps)
                z, norm_cache = th.addcmul(norm.bias.unsqueeze(1), normalised, norm.weight.unsqueeze(1)), (z, mean, inv_std)
            saved.append((z, norm_cache))
            hidden = activation(z)
        return th.baddbmm(self.output_bias.unsqueeze(1), hidden, self.output_weight), saved


def written_out_layers(critic: EnsembleCritic) -> tuple[list[_Block], tuple[th.Tensor, th.Tensor]]:
    """
    The hidden blocks and the output layer ``(weight, bias)`` of ``critic.ensemble`` when it is
    ``[BatchRenorm] Linear [LayerNorm] activation ... [BatchRenorm] Linear(·, 1)`` with the activations of
    :data:`ACTIVATION_BACKWARDS` and any batch renormalisation in running-statistics mode (an affine map, folded into
    the next layer); a ``ValueError`` for any other critic.
    """
    layers: list[list[Any]] = []  # [weight, bias, LayerNorm or None, activation or None] of each Linear
    pending: tuple[th.Tensor, th.Tensor] | None = None  # the folded batch renormalisation before the next Linear
    for module in critic.ensemble:
        if isinstance(module, EnsembleBatchRenorm) and not module.training and pending is None:
            with th.no_grad():
                pending = module.normalisation()
        elif isinstance(module, EnsembleLinear):
            weight: th.Tensor = module.weight
            bias: th.Tensor = module.bias
            if pending is not None:
                gain, shift = pending
                with th.no_grad():  # W (g x + c) + b = (W g) x + (W c + b)
                    bias = th.baddbmm(bias.unsqueeze(1), shift.unsqueeze(1), weight).squeeze(1)
                    weight = weight * gain.unsqueeze(2)
                pending = None
            layers.append([weight, bias, None, None])
        elif isinstance(module, EnsembleLayerNorm) and layers and layers[-1][2:] == [None, None]:
            layers[-1][2] = module
        elif type(module) in ACTIVATION_BACKWARDS and layers and layers[-1][3] is None:
            layers[-1][3] = module
        else:
            raise _unsupported(critic)
    n_outputs = 2 if critic.distributional else 1
    output_ok = len(layers) >= 2 and layers[-1][2:] == [None, None] and layers[-1][0].shape[2] == n_outputs
    if not output_ok or pending is not None or any(layer[3] is None for layer in layers[:-1]):
        raise _unsupported(critic)
    # Q is the first output (a distributional critic's mean)
    return [tuple(layer) for layer in layers[:-1]], (layers[-1][0][..., :1], layers[-1][1][..., :1])  # type: ignore[misc]


def _unsupported(critic: EnsembleCritic) -> ValueError:
    return ValueError(
        "DACERF's Langevin gradient is written out for critics of ensemble Linear layers with "
        f"{', '.join(cls.__name__ for cls in ACTIVATION_BACKWARDS)} activations (optionally LayerNorm or batch "
        f"renormalisation in running-statistics mode) and one output, not for {critic.ensemble}: choose one of those "
        "activation_fn in policy_kwargs."
    )


MlpPolicy = DACERFPolicy


class CnnPolicy(DACERFPolicy):
    """:class:`DACERFPolicy` with ``NatureCNN`` features by default (image observations)."""

    default_features_extractor_class = NatureCNN


class MultiInputPolicy(DACERFPolicy):
    """:class:`DACERFPolicy` with ``CombinedExtractor`` features by default (Dict observations)."""

    default_features_extractor_class = CombinedExtractor
