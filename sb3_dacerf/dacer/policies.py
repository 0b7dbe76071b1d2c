import math
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.torch_layers import CombinedExtractor, NatureCNN, create_mlp
from torch import nn

from sb3_dacerf.common.policies import GenerativeActor, TwinCriticPolicy


def vp_betas(n_steps: int) -> np.ndarray:
    """
    Noise variances ``β_1..β_T`` (``T = n_steps``) of the forward diffusion process: the variance-preserving schedule
    of Diffusion-QL and the official DACER code, ``β_t = 1 - exp(-b_min / T - (b_max - b_min) (2t - 1) / (2 T²))``,
    ``b_min = 0.1``, ``b_max = 10``.
    """
    b_min, b_max = 0.1, 10.0
    t = np.arange(1, n_steps + 1)
    return 1 - np.exp(-b_min / n_steps - 0.5 * (b_max - b_min) * (2 * t - 1) / n_steps**2)


class DiffusionActor(GenerativeActor):
    """
    Diffusion actor of DACER: a noise-prediction network ``ε_θ(s, x_t, t)`` (:attr:`network`) and its DDPM reverse
    process of ``n_diffusion_steps`` steps, each clipping the predicted clean action
    ``x̂_0 = (x_t - sqrt(1 - ᾱ_t) ε_θ) / sqrt(ᾱ_t)`` to [-1, 1] and drawing ``x_{t-1}`` from the posterior
    ``q(x_{t-1} | x_t, x̂_0)``. Its noise ``(batch, n_diffusion_steps, action_dim)`` holds ``x_T = noise[:, 0]`` and
    the posterior noise ``noise[:, t]`` of the step from ``x_t``, ``t = 1 .. T-1`` (none at the last step);
    ``noise=None`` follows the mean path. Takes the arguments of :class:`~sb3_dacerf.common.policies.GenerativeActor`
    (``activation_fn`` also that of the time embedding), and:

    :param n_diffusion_steps: Number of diffusion steps ``T`` (network calls per action)
    :param time_embedding_dim: Size of the sinusoidal time embedding
    """

    own_arguments = ("n_diffusion_steps", "time_embedding_dim")

    def __init__(self, *args: Any, n_diffusion_steps: int = 20, time_embedding_dim: int = 16, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.n_diffusion_steps = n_diffusion_steps
        self.time_embedding_dim = time_embedding_dim

        # Reverse-process coefficients per step t, as Python floats: constants of the schedule, cheap to multiply by
        betas = vp_betas(n_diffusion_steps)
        alphas_cumprod = np.cumprod(1 - betas)
        alphas_cumprod_prev = np.append(1.0, alphas_cumprod[:-1])
        posterior_variance = betas * (1 - alphas_cumprod_prev) / (1 - alphas_cumprod)
        self.reverse_coefficients = [
            (
                float(np.sqrt(1 / alphas_cumprod[t])),  # x̂_0 = c0 x_t - c1 ε
                float(np.sqrt(1 / alphas_cumprod[t] - 1)),
                float(betas[t] * np.sqrt(alphas_cumprod_prev[t]) / (1 - alphas_cumprod[t])),  # mean = m0 x̂_0 + m1 x_t
                float((1 - alphas_cumprod_prev[t]) * np.sqrt(1 - betas[t]) / (1 - alphas_cumprod[t])),
                float(np.sqrt(max(posterior_variance[t], 1e-20))) if t > 0 else 0.0,  # no noise at the last step
            )
            for t in range(n_diffusion_steps)
        ]

        # Time embedding: fixed sinusoidal features of t, then a small MLP, as in the official DACERPolicyNet
        half = time_embedding_dim // 2
        frequencies = 10_000 ** (-th.arange(half) / half)
        angles = th.arange(n_diffusion_steps, dtype=th.float32)[:, None] * frequencies[None, :]
        sinusoids = th.cat([th.sin(angles), th.cos(angles)], dim=1) / math.sqrt(time_embedding_dim)
        self.register_buffer("time_sinusoids", sinusoids, persistent=False)
        self.time_net = nn.Sequential(
            nn.Linear(time_embedding_dim, 2 * time_embedding_dim),
            self.activation_fn(),
            nn.Linear(2 * time_embedding_dim, time_embedding_dim),
        )
        # Input: state features, the noisy action x_t and the time embedding
        input_dim = self.features_dim + self.action_dim + time_embedding_dim
        self.network = nn.Sequential(*create_mlp(input_dim, self.action_dim, self.net_arch, self.activation_fn))

    @property
    def noise_shape(self) -> tuple[int, ...]:
        """``(n_diffusion_steps, action_dim)``: the start ``x_T`` and the posterior noise of each reverse step."""
        return (self.n_diffusion_steps, self.action_dim)

    def time_embeddings(self) -> th.Tensor:
        """The embedding of each diffusion step ``t = 0 .. T-1``, ``(n_diffusion_steps, time_embedding_dim)``."""
        return self.time_net(self.time_sinusoids)

    def sample(self, features: th.Tensor, noise: th.Tensor | None = None) -> th.Tensor:
        """The reverse diffusion process from ``noise`` (see the class description; ``None``: the mean path)."""
        batch_size = features.shape[0]
        time_embeddings = self.time_embeddings().unbind(0)
        if noise is None:
            actions = th.zeros((batch_size, self.action_dim), device=features.device, dtype=features.dtype)
        else:
            actions = noise[:, 0]  # x_T ~ N(0, I), as the official sampler (GaussianDiffusion.p_sample)
        for t in reversed(range(self.n_diffusion_steps)):
            c0, c1, m0, m1, std = self.reverse_coefficients[t]
            predicted_noise = self.network(th.cat([features, actions, time_embeddings[t].expand(batch_size, -1)], dim=1))
            clean_actions = (c0 * actions - c1 * predicted_noise).clamp(-1.0, 1.0)
            actions = m0 * clean_actions + m1 * actions
            if noise is not None and t > 0:
                actions = actions + std * noise[:, t]
        return actions.clamp(-1.0, 1.0)


class DACERPolicy(TwinCriticPolicy):
    """
    Policy class (diffusion actor and twin critics) for DACER. Takes the arguments of
    :class:`~sb3_dacerf.common.policies.TwinCriticPolicy`, with the official code's networks by default
    (``net_arch=[256, 256, 256]``, ``activation_fn=nn.Mish``), and:

    :param n_diffusion_steps: Number of diffusion steps of the actor
    """

    actor_class = DiffusionActor
    actor: DiffusionActor

    default_net_arch = (256, 256, 256)
    default_activation_fn = nn.Mish

    def __init__(self, *args: Any, n_diffusion_steps: int = 20, **kwargs: Any):
        super().__init__(*args, actor_kwargs=dict(n_diffusion_steps=n_diffusion_steps), **kwargs)


MlpPolicy = DACERPolicy


class CnnPolicy(DACERPolicy):
    """:class:`DACERPolicy` with ``NatureCNN`` features by default (image observations)."""

    default_features_extractor_class = NatureCNN


class MultiInputPolicy(DACERPolicy):
    """:class:`DACERPolicy` with ``CombinedExtractor`` features by default (Dict observations)."""

    default_features_extractor_class = CombinedExtractor
