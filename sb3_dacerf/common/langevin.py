"""Langevin dynamics on the critic's energy landscape (Algorithm 1 of the DACER-F paper)."""

import functools
from collections.abc import Callable

import torch as th
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn
from torch.nn.utils import skip_init

from sb3_dacerf.common.utils import is_batch_renorm


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
def compiled_langevin_targets() -> Callable[..., th.Tensor]:
    """:func:`langevin_targets` through ``torch.compile`` (compiled on the first call, ~30 s on a CPU)."""
    return th.compile(langevin_targets, dynamic=False)


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


def _layer_norm_forward(norm: nn.LayerNorm, z: th.Tensor) -> tuple[th.Tensor, tuple[th.Tensor, th.Tensor, th.Tensor]]:
    """``LayerNorm`` with autograd's own kernel, also returning what its backward kernel needs (input, mean, 1/σ)."""
    y, mean, inv_std = th.native_layer_norm(z, norm.normalized_shape, norm.weight, norm.bias, norm.eps)
    return y, (z, mean, inv_std)


def _layer_norm_backward(norm: nn.LayerNorm, grad: th.Tensor, cache: tuple[th.Tensor, th.Tensor, th.Tensor]) -> th.Tensor:
    """dQ/dz from dQ/dy of ``y = LayerNorm(z)``, with autograd's own kernel."""
    z, mean, inv_std = cache
    return th.ops.aten.native_layer_norm_backward(
        grad, z, norm.normalized_shape, mean, inv_std, norm.weight, norm.bias, [True, False, False]
    )[0]


class MinQActionGradient:
    """
    ``∇_a min_j Q_j(s, a)`` of SB3 twin critics (``ContinuousCritic``) at fixed states ``s``.

    Built once per batch of states: the features, and each critic's first-layer contribution of the state, are
    computed once instead of at every Langevin step. For the critics SB3 builds (MLPs of ``Linear`` layers with
    ReLU, LeakyReLU or Tanh between them, optionally a ``LayerNorm`` after each hidden ``Linear`` as in
    :class:`sb3_dacerf.common.policies.LayerNormCritic`, or a batch renormalisation in running-statistics mode
    before each ``Linear`` as in :class:`sb3_dacerf.common.policies.BatchRenormCritic`, folded into that ``Linear``)
    the gradient is written out (forward pass, then the chain
    rule through the same weights) without building an autograd graph: the same numbers as autograd, faster, and
    ``torch.compile`` can fuse it. Other critic networks fall back to autograd on the cached features.
    Per sample, the gradient is that of the critic with the smallest Q (as autograd routes it through ``min``).

    :param critic: Twin critics ``Q_j(s, a) = q_networks[j](concat(features(s), a))``
    :param observations: The fixed states ``s``, a batch
    """

    def __init__(self, critic: ContinuousCritic, observations: PyTorchObs):
        with th.no_grad():
            self.features = critic.extract_features(observations, critic.features_extractor)
        self.q_networks = list(critic.q_networks)
        layers = [_hidden_blocks(_fold_normalisation(q_net)) for q_net in self.q_networks]
        written_out = [layer for layer in layers if layer is not None]
        self.written_out = len(written_out) == len(layers)
        if self.written_out:
            n_features = self.features.shape[1]
            self.networks = []
            with th.no_grad():
                for blocks, output in written_out:
                    first = blocks[0][0]
                    # W [s; a] + b = (W_s s + b) + W_a a: the state part is the same at every Langevin step
                    state_part = self.features @ first.weight[:, :n_features].t()
                    if first.bias is not None:
                        state_part += first.bias
                    self.networks.append((state_part, first.weight[:, n_features:], blocks, output))

    def __call__(self, actions: th.Tensor) -> th.Tensor:
        if not self.written_out:
            return autograd_action_gradient(self._min_q)(actions)
        with th.no_grad():
            q_values, gradients = [], []
            for state_part, action_weight, blocks, output in self.networks:
                # Forward pass through the hidden blocks (Linear, [LayerNorm], activation), keeping what the
                # backward pass needs
                saved = []
                hidden = None
                for index, (linear, norm, activation) in enumerate(blocks):
                    z = th.addmm(state_part, actions, action_weight.t()) if index == 0 else linear(hidden)
                    norm_cache = None
                    if norm is not None:
                        z, norm_cache = _layer_norm_forward(norm, z)
                    saved.append((z, norm_cache))
                    hidden = activation(z)
                q_values.append(output(hidden))
                # Backward pass: from the output layer down to the action input
                gradient = output.weight.expand(actions.shape[0], -1)
                for index in range(len(blocks) - 1, -1, -1):
                    linear, norm, activation = blocks[index]
                    z, norm_cache = saved[index]
                    gradient = _ACTIVATION_BACKWARDS[type(activation)](activation, gradient, z)
                    if norm is not None and norm_cache is not None:  # both or neither
                        gradient = _layer_norm_backward(norm, gradient, norm_cache)
                    gradient = gradient @ (action_weight if index == 0 else linear.weight)
                gradients.append(gradient)
            # The gradient of the smallest Q, per sample (the first one on ties, as autograd through th.min)
            if len(gradients) == 2:
                return th.where(q_values[0] <= q_values[1], gradients[0], gradients[1])
            smallest = th.stack(q_values).argmin(dim=0, keepdim=True)  # (1, batch, 1)
            stacked = th.stack(gradients)  # (n_critics, batch, action_dim)
            return stacked.gather(0, smallest.expand(1, *stacked.shape[1:])).squeeze(0)

    def _min_q(self, actions: th.Tensor) -> th.Tensor:
        inputs = th.cat([self.features, actions], dim=1)
        return th.min(th.cat([q_net(inputs) for q_net in self.q_networks], dim=1), dim=1, keepdim=True).values


def _fold_normalisation(network: nn.Module) -> nn.Module:
    """
    ``network`` with each batch renormalisation in running-statistics mode folded into the ``Linear`` after it (in
    that mode it is the affine map ``scale · (x - mean) / sqrt(var + eps) + bias``): new layers, the same function.
    ``network`` itself when it has none, or one in training mode, or one not followed by a ``Linear``.
    """
    if not isinstance(network, nn.Sequential) or not any(is_batch_renorm(module) for module in network):
        return network
    modules = list(network)
    folded: list[nn.Module] = []
    index = 0
    while index < len(modules):
        module = modules[index]
        if not is_batch_renorm(module):
            folded.append(module)
            index += 1
            continue
        linear = modules[index + 1] if index + 1 < len(modules) else None
        if module.training or not module.affine or not isinstance(linear, nn.Linear):
            return network
        with th.no_grad():
            scale, bias, mean, var, eps = (getattr(module, name) for name in ("scale", "bias", "ra_mean", "ra_var", "eps"))
            gain = scale / (var + eps).sqrt()
            shift = bias - gain * mean
            # This runs at every actor update: skip the random initialisation that the copies below overwrite
            weight = linear.weight
            merged = skip_init(nn.Linear, linear.in_features, linear.out_features, device=weight.device, dtype=weight.dtype)
            merged.weight.copy_(weight * gain)
            merged.bias.copy_(weight @ shift + (linear.bias if linear.bias is not None else 0.0))
        folded.append(merged)
        index += 2
    return nn.Sequential(*folded)


def _hidden_blocks(network: nn.Module) -> tuple[list[tuple[nn.Linear, nn.LayerNorm | None, nn.Module]], nn.Linear] | None:
    """
    The hidden blocks ``(Linear, LayerNorm or None, activation)`` and the output layer of
    ``Linear, [LayerNorm], act, ..., Linear, [LayerNorm], act, Linear(·, 1)``, or None when ``network`` is anything else.
    """
    if not isinstance(network, nn.Sequential):
        return None
    modules = list(network)
    blocks: list[tuple[nn.Linear, nn.LayerNorm | None, nn.Module]] = []
    index = 0
    while index < len(modules) - 1:
        linear = modules[index]
        following = modules[index + 1] if index + 1 < len(modules) else None
        norm = following if type(following) is nn.LayerNorm else None
        position = index + (2 if norm is not None else 1)
        if position >= len(modules) or type(linear) is not nn.Linear:
            return None
        activation = modules[position]
        if type(activation) not in _ACTIVATION_BACKWARDS:
            return None
        if norm is not None and len(norm.normalized_shape) != 1:
            return None
        blocks.append((linear, norm, activation))
        index = position + 1
    output = modules[-1] if modules else None
    if not blocks or index != len(modules) - 1 or type(output) is not nn.Linear or output.out_features != 1:
        return None
    return blocks, output
