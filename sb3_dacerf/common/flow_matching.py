"""The flow-matching actor loss of DACER-F: the imitation term towards Langevin targets and its balance with ``-Q``."""

from collections.abc import Callable

import torch as th
from torch.nn import functional as F

#: The weightings of the two terms of the actor loss (``flow_matching_weights``), see :func:`actor_loss_weights`
FLOW_MATCHING_WEIGHTS = ("gain", "paper", "q_scale")


def flow_matching_loss(
    velocity: Callable[[th.Tensor, th.Tensor], th.Tensor],
    targets: th.Tensor,
    noise: th.Tensor | None = None,
    time: th.Tensor | None = None,
) -> th.Tensor:
    """
    Conditional flow matching towards ``targets`` on the straight path ``a_t = (1 - t) a_0 + t a*``, whose
    velocity is ``a* - a_0``: the per-sample error ``||v(a_t, t) - (a* - a_0)||²``.

    :param velocity: Maps points ``a_t`` ``(batch, action_dim)`` and times ``t`` ``(batch, 1)`` to the predicted
        velocity ``v(s, a_t, t)``, the states bound inside it
    :param targets: The target actions ``a*`` (e.g. Langevin targets), ``(batch, action_dim)``
    :param noise: The path's starting points ``a_0``; ``N(0, I)`` draws by default
    :param time: The times ``t``; ``U[0, 1]`` draws by default
    :return: The squared error of each sample, ``(batch, 1)``
    """
    noise = th.randn_like(targets) if noise is None else noise
    time = th.rand((targets.shape[0], 1), device=targets.device, dtype=targets.dtype) if time is None else time
    actions_t = (1 - time) * noise + time * targets
    return (velocity(actions_t, time) - (targets - noise)).pow(2).sum(dim=1, keepdim=True)


def actor_loss_weights(
    method: str,
    q_values_pi: th.Tensor,
    q_values_star: th.Tensor,
    q_values_buffer: th.Tensor,
    coef: float = 1.0,
) -> tuple[th.Tensor, th.Tensor]:
    """
    Weights of the actor loss ``J_F = mean(-Q(s, π(s)) / κ + λ_f ||v - (a* - a_0)||²)``: the scale ``κ`` of the
    improvement term and the per-sample weight ``λ_f`` of the flow-matching (imitation) term.

    All of them keep the paper's ``λ_f ∝ g = ReLU(Q(s, a*) - Q(s, a_B))``, the Langevin gain of each sample,
    normalised by its batch mean; they differ in how the two terms are put on one scale:

    - ``"gain"``: ``κ = mean(g)``. Both terms are then free of the reward's scale and shift (``-Q / κ`` has the
      gradient of ``Q`` in units of the batch's Langevin gain). ``κ`` is floored at ``1e-3`` of the batch's mean
      absolute deviation of ``Q(s, a_B)`` for batches where Langevin dynamics found no gain.
    - ``"paper"``: ``κ = 1`` and ``λ_f = coef * g``, the paper's ``λ_f ∝ ReLU(Q(s, a*) - Q(s, a_B))`` taken literally
      (not normalised by the batch's mean gain). ``g`` is a difference of Q-values, so the weight does not move with
      a shift of the reward; both terms grow linearly with the reward's scale, so their balance does not move with it
      either. The proportionality constant, which the paper does not give, is ``coef``.
    - ``"q_scale"``: ``κ = 1`` and ``λ_f = coef * mean|Q(s, π(s))| * g / mean(g)``: the imitation term grows
      with ``|Q|``, so it depends on a shift of the reward (the weighting of version 0.1.0, kept to reproduce it).

    :param method: One of :data:`FLOW_MATCHING_WEIGHTS`
    :param q_values_pi: ``Q(s, π(s))``, ``(batch, 1)`` (only its value is used)
    :param q_values_star: ``Q(s, a*)`` of the Langevin targets, ``(batch, 1)``
    :param q_values_buffer: ``Q(s, a_B)`` of the replay actions the targets started from, ``(batch, 1)``
    :param coef: ``flow_matching_coef``, the weight of the imitation term
    :return: ``κ`` (a scalar tensor) and ``λ_f`` ``(batch, 1)``, both detached
    """
    with th.no_grad():
        gain = F.relu(q_values_star - q_values_buffer)
        mean_gain = gain.mean()
        relative_gain = gain / mean_gain.clamp_min(1e-12)
        if method == "gain":
            q_spread = (q_values_buffer - q_values_buffer.mean()).abs().mean()
            kappa = th.maximum(mean_gain, 1e-3 * q_spread).clamp_min(1e-8)
            return kappa, coef * relative_gain
        if method == "paper":
            return th.ones_like(mean_gain), coef * gain
        if method == "q_scale":
            return th.ones_like(mean_gain), coef * q_values_pi.abs().mean() * relative_gain
    raise ValueError(f"Unknown flow_matching_weights={method!r}: it must be one of {', '.join(FLOW_MATCHING_WEIGHTS)}.")
