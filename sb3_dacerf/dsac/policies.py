import math
from typing import Any, cast

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, NatureCNN, create_mlp
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn
from torch.nn import functional as F

from sb3_dacerf.common.policies import Actor, TwinCriticPolicy

#: Added to ``1 - tanh(u)²`` in the log-density of a tanh-squashed action, as in the authors' code and SB3
TANH_EPSILON = 1e-6


class GaussianActor(Actor):
    """
    Tanh-Gaussian actor of DSAC: ``a = tanh(u)``, ``u = μ(s) + σ(s) ξ``, ``ξ ~ N(0, I)`` its noise, with ``μ`` and
    ``log σ`` the two halves of the output of one network (:attr:`network`, as the authors' ``mlp_shared`` policy)
    and ``log σ`` clipped to ``[log_std_min, log_std_max]``. Takes the arguments of
    :class:`~sb3_dacerf.common.policies.Actor`, and:

    :param log_std_min: Lower clip of ``log σ`` (-20, the authors' and SB3's)
    :param log_std_max: Upper clip of ``log σ`` (0.5, the authors'; SB3's SAC uses 2)
    """

    own_arguments = ("log_std_min", "log_std_max")

    def __init__(self, *args: Any, log_std_min: float = -20.0, log_std_max: float = 0.5, **kwargs: Any):
        super().__init__(*args, **kwargs)
        if not (math.isfinite(log_std_min) and math.isfinite(log_std_max) and log_std_min < log_std_max):
            raise ValueError(
                f"Invalid log_std_min={log_std_min!r}, log_std_max={log_std_max!r}: they must be finite numbers with "
                "log_std_min < log_std_max (the authors' are -20 and 0.5)"
            )
        self.log_std_min = float(log_std_min)
        self.log_std_max = float(log_std_max)
        self.network = nn.Sequential(*create_mlp(self.features_dim, 2 * self.action_dim, self.net_arch, self.activation_fn))

    @property
    def noise_shape(self) -> tuple[int, ...]:
        return (self.action_dim,)

    def distribution_parameters(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """``μ`` and the clipped ``log σ`` of the Gaussian before the tanh, each ``(batch, action_dim)``."""
        mean, log_std = self.network(features).chunk(2, dim=-1)
        return mean, log_std.clamp(self.log_std_min, self.log_std_max)

    def sample(self, features: th.Tensor, noise: th.Tensor | None = None) -> th.Tensor:
        """``tanh(μ + σ ξ)``, ``ξ`` the ``noise`` ``(batch or 1, action_dim)``; ``None``: ``tanh(μ)``."""
        mean, log_std = self.distribution_parameters(features)
        if noise is None:
            return th.tanh(mean)
        return th.tanh(mean + log_std.exp() * noise)

    def sample_with_log_prob(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """A reparameterised sample ``a = tanh(u)`` ``(batch, action_dim)`` and its log-density
        ``log π(a|s) = log N(u; μ, σ²) - Σ log(1 - tanh(u)² + 1e-6)`` ``(batch,)``."""
        mean, log_std = self.distribution_parameters(features)
        std = log_std.exp()
        gaussian = mean + std * th.randn_like(mean)
        actions = th.tanh(gaussian)
        log_prob = th.distributions.Normal(mean, std).log_prob(gaussian).sum(dim=-1)
        log_prob = log_prob - th.log(1 - actions.pow(2) + TANH_EPSILON).sum(dim=-1)
        return actions, log_prob

    def action_log_prob(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """:meth:`sample_with_log_prob` from observations (SB3's ``sac.policies.Actor.action_log_prob``)."""
        return self.sample_with_log_prob(self.extract_features(obs, self.features_extractor))


class GaussianCritic(BaseModel):
    """
    Twin distributional critics of DSAC: each network ``qf<j>`` outputs the mean ``Q(s, a)`` and the standard
    deviation ``σ(s, a) = softplus(·)`` of a Gaussian return (the authors' ``ActionValueDistri``). Called, it returns
    the means; :meth:`distributions` also the standard deviations. Same arguments as SB3's ``ContinuousCritic``, and:

    :param layer_norm: ``LayerNorm`` after every hidden linear layer (before the activation)
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
        layer_norm: bool = False,
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        self.share_features_extractor = share_features_extractor
        self.n_critics = n_critics
        input_dim = features_dim + get_action_dim(action_space)
        post_linear_modules: list[type[nn.Module]] | None = [nn.LayerNorm] if layer_norm else None
        networks = [
            nn.Sequential(*create_mlp(input_dim, 2, net_arch, activation_fn, post_linear_modules=post_linear_modules))
            for _ in range(n_critics)
        ]
        for idx, q_net in enumerate(networks):
            self.add_module(f"qf{idx}", q_net)
        self.q_networks = networks  # a list, as SB3's ContinuousCritic: the networks are saved once, as qf<j>

    def distributions(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[tuple[th.Tensor, th.Tensor], ...]:
        """One ``(mean, std)`` pair per network, each ``(batch, 1)``, at observations and actions in [-1, 1]."""
        with th.set_grad_enabled(not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        qvalue_input = th.cat([features, actions], dim=1)
        outputs = [q_net(qvalue_input).chunk(2, dim=-1) for q_net in self.q_networks]
        return tuple((mean, F.softplus(raw_std)) for mean, raw_std in outputs)

    def forward(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        return tuple(mean for mean, _ in self.distributions(obs, actions))


class DSACPolicy(TwinCriticPolicy):
    """
    Policy class (tanh-Gaussian actor, twin Gaussian critics, and target networks of both) for DSAC. Takes the
    arguments of :class:`~sb3_dacerf.common.policies.TwinCriticPolicy` (``critic``: ``"mlp"`` or ``"layer_norm"``),
    with the authors' networks by default (``net_arch=[256, 256, 256]``, ``activation_fn=nn.GELU``), and:

    :param log_std_min: Lower clip of the actor's ``log σ``
    :param log_std_max: Upper clip of the actor's ``log σ``
    """

    actor_class = GaussianActor
    actor: GaussianActor
    actor_target: GaussianActor
    critic: GaussianCritic
    critic_target: GaussianCritic

    default_net_arch = (256, 256, 256)
    default_activation_fn = nn.GELU

    def __init__(
        self,
        *args: Any,
        log_std_min: float = -20.0,
        log_std_max: float = 0.5,
        n_critics: int = 2,
        critic: str = "mlp",
        **kwargs: Any,
    ):
        if critic == "batch_renorm":
            raise ValueError(
                "DSAC does not support critic='batch_renorm': its targets come from the target critics' return "
                "distributions. Use critic='layer_norm' for normalised critics, or DACERF for CrossQ's critics."
            )
        if n_critics != 2:
            raise ValueError(
                f"DSAC has exactly two critics (the target takes the smaller of two means with its sample): "
                f"n_critics={n_critics!r} must be 2"
            )
        super().__init__(
            *args,
            n_critics=n_critics,
            critic=critic,
            actor_kwargs=dict(log_std_min=log_std_min, log_std_max=log_std_max),
            **kwargs,
        )

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)
        # Target policy network of DSAC-T: a' ~ π̄(·|s') in the critic target
        self.actor_target = cast(GaussianActor, self.make_actor(features_extractor=None))
        self.actor_target.load_state_dict(self.actor.state_dict())
        self.actor_target.set_training_mode(False)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> GaussianCritic:
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return GaussianCritic(**critic_kwargs, layer_norm=self.critic_kind == "layer_norm").to(self.device)


MlpPolicy = DSACPolicy


class CnnPolicy(DSACPolicy):
    """:class:`DSACPolicy` with ``NatureCNN`` features by default (image observations)."""

    default_features_extractor_class = NatureCNN


class MultiInputPolicy(DSACPolicy):
    """:class:`DSACPolicy` with ``CombinedExtractor`` features by default (Dict observations)."""

    default_features_extractor_class = CombinedExtractor
