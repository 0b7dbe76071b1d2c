"""Langevin dynamics on the critic's energy landscape (Algorithm 1 of the DACER-F paper)."""

from collections.abc import Callable

import torch as th


def langevin_targets(
    q_function: Callable[[th.Tensor], th.Tensor],
    actions: th.Tensor,
    n_steps: int,
    step_size: float,
    temperature: float,
    low: float = -1.0,
    high: float = 1.0,
) -> th.Tensor:
    """
    Move actions towards samples of ``p(a|s) ∝ exp(Q(s, a) / temperature)`` with unadjusted Langevin dynamics:
    ``a <- clip(a + step_size * ∇_a Q(s, a) + sqrt(2 * step_size * temperature) * ξ, low, high)``, ``ξ ~ N(0, I)``.

    Gradients are taken with respect to the actions only: freeze the critic's parameters around this call
    (see :func:`sb3_dacerf.common.utils.frozen`) so that no parameter gradient is computed or accumulated.

    With a finite number of steps the result is not yet a Boltzmann sample: ``n_steps * step_size`` bounds
    how far the mean can travel along ``∇_a Q`` (0.6 gradient units with the paper's 20 x 0.03).

    :param q_function: Maps a batch of actions ``(batch, action_dim)`` to Q-values ``(batch, 1)``;
        the observations are bound inside it.
    :param actions: Starting actions ``a_B`` (e.g. from the replay buffer), in the policy's [-1, 1] space
    :param n_steps: Number of Langevin steps ``N_l``
    :param step_size: Step size ``η_a``
    :param temperature: Temperature ``α`` of the energy-based target
    :param low: Lower bound the actions are clipped to after every step
    :param high: Upper bound the actions are clipped to after every step
    :return: The improved actions ``a*``, detached from any graph
    """
    noise_scale = (2.0 * step_size * temperature) ** 0.5
    # All the noise is drawn at once: one allocation instead of one per step
    noise = th.randn((n_steps, *actions.shape), device=actions.device, dtype=actions.dtype).mul_(noise_scale)
    action = actions.detach()
    for step in range(n_steps):
        with th.enable_grad():
            action.requires_grad_(True)
            (grad,) = th.autograd.grad(q_function(action).sum(), action)
        action = (action.detach() + step_size * grad + noise[step]).clamp_(low, high)
    return action
