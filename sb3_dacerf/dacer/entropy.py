"""Entropy of a sampled policy, estimated with a Gaussian mixture as in DACER."""

import math

import torch as th


@th.no_grad()
def gaussian_mixture_entropy(
    samples: th.Tensor, n_components: int = 3, n_iterations: int = 100, tolerance: float = 1e-3, min_variance: float = 1e-6
) -> th.Tensor:
    """
    DACER's entropy estimate ``H ≈ Σ_k w_k H(N(μ_k, Σ_k)) - Σ_k w_k log w_k`` of a Gaussian mixture with diagonal
    covariances fitted to the samples of each state by expectation-maximisation (all the states at once).

    :param samples: Actions sampled from the policy, ``(n_states, n_samples, action_dim)``
    :param n_components: Number of mixture components ``K``
    :param n_iterations: Maximum number of EM iterations
    :param tolerance: Stop when no state's mean log-likelihood changed by more than this (sklearn's default)
    :param min_variance: Added to every variance (actions clipped at a bound keep a finite log-density)
    :return: The entropy estimate of each state, ``(n_states,)``
    """
    n_states, n_samples, action_dim = samples.shape
    # Initialisation: means at K samples spread out greedily (a random one, then each time the sample farthest
    # from the means so far), the state's variance, equal weights
    index = th.randint(n_samples, (n_states, 1), device=samples.device)
    means = th.gather(samples, 1, index[:, :, None].expand(-1, -1, action_dim))
    for _ in range(n_components - 1):
        distances = th.cdist(samples, means).min(dim=2).values  # (n_states, n_samples)
        farthest = distances.argmax(dim=1, keepdim=True)
        means = th.cat([means, th.gather(samples, 1, farthest[:, :, None].expand(-1, -1, action_dim))], dim=1)
    variances = samples.var(dim=1, keepdim=True).expand(-1, n_components, -1) + min_variance
    log_weights = th.full((n_states, n_components), -math.log(n_components), device=samples.device)

    log_likelihood = th.full((n_states,), -math.inf, device=samples.device)
    for _ in range(n_iterations):
        # E-step: responsibilities r_nk ∝ w_k N(x_n; μ_k, Σ_k), the squared distances as batched matrix products
        precisions = 1.0 / variances  # (n_states, K, action_dim)
        squared_distances = (
            samples.pow(2) @ precisions.transpose(1, 2)
            - 2 * samples @ (means * precisions).transpose(1, 2)
            + (means.pow(2) * precisions).sum(-1)[:, None, :]
        )  # (n_states, n_samples, K)
        log_normalisers = -0.5 * (variances.log().sum(-1) + action_dim * math.log(2 * math.pi))  # (n_states, K)
        log_joint = log_weights[:, None, :] + log_normalisers[:, None, :] - 0.5 * squared_distances
        previous_log_likelihood, log_likelihood = log_likelihood, log_joint.logsumexp(dim=2).mean(dim=1)
        if (log_likelihood - previous_log_likelihood).abs().max() < tolerance:
            break
        responsibilities = (log_joint - log_joint.logsumexp(dim=2, keepdim=True)).exp()
        # M-step: weights, means and variances from the responsibilities
        counts = responsibilities.sum(dim=1) + 1e-10  # (n_states, K)
        log_weights = (counts / n_samples).log()
        means = responsibilities.transpose(1, 2) @ samples / counts[:, :, None]
        second_moments = responsibilities.transpose(1, 2) @ samples.pow(2) / counts[:, :, None]
        variances = (second_moments - means.pow(2)).clamp_min(0.0) + min_variance

    component_entropies = 0.5 * (action_dim * (1 + math.log(2 * math.pi)) + variances.log().sum(-1))  # (n_states, K)
    weights = log_weights.exp()
    return (weights * component_entropies).sum(-1) - (weights * log_weights).sum(-1)
