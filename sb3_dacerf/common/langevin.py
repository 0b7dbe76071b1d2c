"""Langevin dynamics on the critic's energy landscape (Algorithm 1 of the DACER-F paper)."""

import functools
from collections.abc import Callable
from typing import Any

import torch as th
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn

from sb3_dacerf.common.ensemble import EnsembleBatchRenorm, EnsembleCritic, EnsembleLayerNorm, EnsembleLinear


def langevin_targets(
    action_gradient: Callable[[th.Tensor], th.Tensor],
    actions: th.Tensor,
    n_steps: int,
    step_size: float,
    temperature: float,
    low: float = -1.0,
    high: float = 1.0,
    normalize_gradient: bool = False,
) -> th.Tensor:
    """
    Move actions towards samples of ``p(a|s) ∝ exp(Q(s, a) / temperature)`` with unadjusted Langevin dynamics:
    ``a <- clip(a + step_size * ∇_a Q(s, a) + sqrt(2 * step_size * temperature) * ξ, low, high)``, ``ξ ~ N(0, I)``.

    With a finite number of steps the result is not yet a Boltzmann sample: ``n_steps * step_size`` bounds
    how far the mean can travel along ``∇_a Q`` (0.6 gradient units with the paper's 20 x 0.03).

    :param action_gradient: Maps a batch of actions ``(batch, action_dim)`` to ``∇_a Q(s, a)`` of the same shape,
        the observations bound inside it: :class:`MinQActionGradient` for twin critics, or
        :func:`autograd_action_gradient` for any differentiable Q-function
    :param actions: Starting actions ``a_B`` (e.g. from the replay buffer), in the policy's [-1, 1] space
    :param n_steps: Number of Langevin steps ``N_l``
    :param step_size: Step size ``η_a``
    :param temperature: Temperature ``α`` of the energy-based target
    :param low: Lower bound the actions are clipped to after every step
    :param high: Upper bound the actions are clipped to after every step
    :param normalize_gradient: Divide ``∇_a Q`` by ``max(1, mean |∇_a Q|)`` (the mean over the batch and the action
        coordinates) at every step, so that the mean move per coordinate stays within ``step_size``: the gradient
        grows with the reward's scale, and with returns in the thousands unnormalised steps carry most targets to
        the action bounds
    :return: The improved actions ``a*``, detached from any graph
    """
    noise_scale = (2.0 * step_size * temperature) ** 0.5
    # All the noise is drawn at once: one allocation instead of one per step
    noise = th.randn((n_steps, *actions.shape), device=actions.device, dtype=actions.dtype).mul_(noise_scale)
    action = actions.detach()
    for step in range(n_steps):
        gradient = action_gradient(action)
        if normalize_gradient:
            gradient = gradient / gradient.abs().mean().clamp(min=1.0)
        action = (action + step_size * gradient + noise[step]).clamp(low, high)
    return action.detach()


@functools.cache
def autograd_action_gradient(q_function: Callable[[th.Tensor], th.Tensor]) -> Callable[[th.Tensor], th.Tensor]:
    """
    ``∇_a Q(a)`` of any differentiable ``q_function`` (batch of actions to ``(batch, 1)`` Q-values), by autograd.

    Freeze the parameters of the networks inside ``q_function`` around the Langevin loop
    (:func:`sb3_dacerf.common.utils.frozen`) so that no parameter gradient is computed.
    """

    def gradient(actions: th.Tensor) -> th.Tensor:
        with th.enable_grad():
            actions = actions.detach().requires_grad_(True)
            (grad,) = th.autograd.grad(q_function(actions).sum(), actions)
        return grad

    return gradient


# Backward pass of each supported activation: dQ/dz from dQ/dh, h = activation(z) (the kernels autograd uses)
_ACTIVATION_BACKWARDS: dict[type[nn.Module], Callable[[nn.Module, th.Tensor, th.Tensor], th.Tensor]] = {
    nn.ReLU: lambda module, grad, z: th.ops.aten.threshold_backward(grad, z, 0.0),
    nn.LeakyReLU: lambda module, grad, z: th.ops.aten.leaky_relu_backward(grad, z, module.negative_slope, False),
    nn.Tanh: lambda module, grad, z: th.ops.aten.tanh_backward(grad, th.tanh(z)),
}


# A hidden block of a written-out critic: (weight (n, in, out), bias (n, out), LayerNorm or None, activation)
_Block = tuple[th.Tensor, th.Tensor, EnsembleLayerNorm | None, nn.Module]


def _layer_norm_forward(norm: EnsembleLayerNorm, z: th.Tensor) -> tuple[th.Tensor, tuple[th.Tensor, th.Tensor, th.Tensor]]:
    """The ensemble ``LayerNorm`` with autograd's own kernel, also returning what its backward needs (input, mean, 1/σ)."""
    normalised, mean, inv_std = th.native_layer_norm(z, (norm.num_features,), None, None, norm.eps)
    return th.addcmul(norm.bias.unsqueeze(1), normalised, norm.weight.unsqueeze(1)), (z, mean, inv_std)


def _layer_norm_backward(
    norm: EnsembleLayerNorm, grad: th.Tensor, cache: tuple[th.Tensor, th.Tensor, th.Tensor], member: int, rows: th.Tensor
) -> th.Tensor:
    """dQ/dz from dQ/dy of ``y = LayerNorm(z)`` for one ensemble member at the samples ``rows``, with autograd's own
    kernel."""
    z, mean, inv_std = (tensor[member].index_select(0, rows) for tensor in cache)
    return th.ops.aten.native_layer_norm_backward(
        grad * norm.weight[member], z, (norm.num_features,), mean, inv_std, None, None, [True, False, False]
    )[0]


class MinQActionGradient:
    """
    ``∇_a min_j Q_j(s, a)`` of ensemble critics (:class:`~sb3_dacerf.common.ensemble.EnsembleCritic`) at fixed
    states ``s``.

    Built once per batch of states: the features, and every critic's first-layer contribution of the state, are
    computed once instead of at every Langevin step. For the critics this package builds (ensemble ``Linear`` layers
    with ReLU, LeakyReLU or Tanh between them, optionally a ``LayerNorm`` after each hidden layer as in
    :class:`~sb3_dacerf.common.ensemble.LayerNormCritic`, or a batch renormalisation in running-statistics mode before
    each layer as in :class:`~sb3_dacerf.common.ensemble.BatchRenormCritic`, folded into that layer) the gradient is
    written out without building an autograd graph: the forward pass runs all the critics in one batched product per
    layer, and the chain rule then goes back through the weights of the critic with the smallest Q only, per sample
    (as autograd routes the gradient through ``min``), so each backward product covers the batch once. The same
    numbers as autograd, faster. Other critics (other activations, an SB3 ``ContinuousCritic``) fall back to autograd
    on the cached features.

    The first call also keeps ``min_j Q_j`` at the actions it was given in :attr:`start_min_q`: the Langevin loop's
    first call is at its starting actions, whose Q-values are then known without another pass.

    :param critic: The critics ``Q_j(s, a)``, an ``EnsembleCritic`` (or any critic with SB3's ``q_networks``)
    :param observations: The fixed states ``s``, a batch
    """

    def __init__(self, critic: Any, observations: PyTorchObs):
        self.critic = critic
        #: ``min_j Q_j(s, a)`` at the actions of the first call, ``(batch, 1)``, detached (``None`` before it)
        self.start_min_q: th.Tensor | None = None
        with th.no_grad():
            self.features = critic.extract_features(observations, critic.features_extractor)
        plan = _written_out_plan(critic) if isinstance(critic, EnsembleCritic) else None
        self.written_out = plan is not None
        if plan is not None:
            self.blocks, (self.output_weight, self.output_bias) = plan
            first_weight, first_bias = self.blocks[0][0], self.blocks[0][1]
            n_members, n_features = first_weight.shape[0], self.features.shape[1]
            with th.no_grad():
                # W [s; a] + b = (W_s s + b) + W_a a: the state part is the same at every Langevin step
                self.state_part = th.baddbmm(
                    first_bias.unsqueeze(1), self.features.expand(n_members, *self.features.shape), first_weight[:, :n_features]
                )
            self.action_weight = first_weight[:, n_features:]

    def __call__(self, actions: th.Tensor) -> th.Tensor:
        if not self.written_out:
            with th.enable_grad():
                actions = actions.detach().requires_grad_(True)
                min_q = self._autograd_min_q(actions)
                (gradient,) = th.autograd.grad(min_q.sum(), actions)
            self._keep_start(min_q.detach())
            return gradient
        with th.no_grad():
            q_values, saved = self._forward(actions)
            # Per sample, only the critic with the smallest Q is differentiated (the first one on ties, as autograd
            # routes the gradient through th.min): the backward pass runs once per critic on its own samples, so
            # each layer's product covers the batch once instead of once per critic
            min_q, smallest = q_values.min(dim=0)
            self._keep_start(min_q)
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
            gradient = _ACTIVATION_BACKWARDS[type(activation)](activation, gradient, z[member].index_select(0, rows))
            if norm is not None and norm_cache is not None:  # both or neither
                gradient = _layer_norm_backward(norm, gradient, norm_cache, member, rows)
            gradient = gradient @ (self.action_weight if index == 0 else weight)[member].t()
        return gradient

    def min_q(self, actions: th.Tensor) -> th.Tensor:
        """``min_j Q_j(s, a)`` at the fixed states, ``(batch, 1)``, without gradient (one forward pass)."""
        with th.no_grad():
            if not self.written_out:
                return self._autograd_min_q(actions)
            return self._forward(actions)[0].min(dim=0).values

    def _keep_start(self, min_q: th.Tensor) -> None:
        if self.start_min_q is None:
            self.start_min_q = min_q

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
            if norm is not None:
                z, norm_cache = _layer_norm_forward(norm, z)
            saved.append((z, norm_cache))
            hidden = activation(z)
        return th.baddbmm(self.output_bias.unsqueeze(1), hidden, self.output_weight), saved

    def _autograd_min_q(self, actions: th.Tensor) -> th.Tensor:
        if isinstance(self.critic, EnsembleCritic):
            return self.critic.q_values_of_features(self.features, actions).min(dim=0).values
        inputs = th.cat([self.features, actions], dim=1)
        return th.min(th.cat([q_net(inputs) for q_net in self.critic.q_networks], dim=1), dim=1, keepdim=True).values


def _written_out_plan(critic: EnsembleCritic) -> tuple[list[_Block], tuple[th.Tensor, th.Tensor]] | None:
    """
    The hidden blocks and the output layer ``(weight, bias)`` of ``critic.ensemble`` when it is
    ``[BatchRenorm] Linear [LayerNorm] activation ... [BatchRenorm] Linear(·, 1)`` with written-out activations and
    any batch renormalisation in running-statistics mode (folded into the next layer: in that mode it is the affine
    map ``gain · x + shift``), else None.
    """
    blocks: list[_Block] = []
    pending: tuple[th.Tensor, th.Tensor] | None = None  # the folded batch renormalisation before the next Linear
    modules = list(critic.ensemble)
    index = 0
    output: tuple[th.Tensor, th.Tensor] | None = None
    while index < len(modules):
        module = modules[index]
        if isinstance(module, EnsembleBatchRenorm):
            if module.training or pending is not None:
                return None
            with th.no_grad():
                pending = module.normalisation()
            index += 1
            continue
        if not isinstance(module, EnsembleLinear):
            return None
        weight: th.Tensor = module.weight
        bias: th.Tensor = module.bias
        if pending is not None:
            gain, shift = pending
            with th.no_grad():
                weight, bias = weight * gain.unsqueeze(2), th.baddbmm(bias.unsqueeze(1), shift.unsqueeze(1), weight).squeeze(1)
            pending = None
        if index == len(modules) - 1:
            if module.out_features != 1:
                return None
            output = (weight, bias)
            break
        norm = modules[index + 1] if isinstance(modules[index + 1], EnsembleLayerNorm) else None
        position = index + (2 if norm is not None else 1)
        if position >= len(modules) or type(modules[position]) not in _ACTIVATION_BACKWARDS:
            return None
        blocks.append((weight, bias, norm, modules[position]))  # type: ignore[arg-type]
        index = position + 1
    if output is None or not blocks:
        return None
    return blocks, output
