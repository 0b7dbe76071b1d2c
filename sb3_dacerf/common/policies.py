"""What the DACER-F and DACER policies share: a generative actor built by the subclass, twin critics and their targets."""

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import (
    BaseFeaturesExtractor,
    FlattenExtractor,
    get_actor_critic_arch,
)
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_dacerf.common.ensemble import BatchRenormCritic, EnsembleCritic, LayerNormCritic
from sb3_dacerf.common.optim import get_optimizer_class

#: The critics of :class:`TwinCriticPolicy` (its ``critic`` argument)
CRITICS = ("mlp", "layer_norm", "batch_renorm")


class GenerativeActor(BasePolicy, ABC):
    """
    Base of the actors of this package (:class:`sb3_dacerf.dacerf.policies.FlowActor` of DACERF,
    :class:`sb3_dacerf.dacer.policies.DiffusionActor` of DACER): a generator that turns noise into an action in
    [-1, 1] with a network ``network`` of (state features, action, time), and Gaussian exploration noise on top
    (``squash_output``: the algorithm rescales [-1, 1] to the action space's bounds).

    The contract both actors follow:

    - ``forward(obs, deterministic=False)``: actions in [-1, 1], as SB3's actors (``predict``, rollouts, the
      critic target); :meth:`act` does the same from state features.
    - :meth:`sample` ``(features, noise=None)``: the generator alone, a deterministic function of the noise,
      differentiable with respect to the network, without exploration noise. ``noise=None`` is the noise's mean
      (zeros): the deterministic action.
    - :meth:`draw_noise` ``(features)``: random noise for :meth:`sample`, of shape ``(batch, *noise_shape)``.
    - :meth:`add_exploration_noise` ``(actions)``: ``clip(a + exploration_std · ξ, -1, 1)``, ``ξ ~ N(0, I)``,
      with ``exploration_std = exploration_noise_scale · exp(log_alpha)`` (none when ``log_alpha = -inf``).

    Stochastic actions are ``add_exploration_noise(sample(features, draw_noise(features)))``; deterministic actions
    are ``sample(features)``. A generative policy has no tractable log-density, hence no ``action_log_prob``: each
    algorithm estimates the policy's entropy from samples.

    :param observation_space: Observation space
    :param action_space: Action space
    :param net_arch: Hidden layer sizes of the network
    :param features_extractor: Network to extract features
        (a CNN when using images, a nn.Flatten() layer otherwise)
    :param features_dim: Number of features
    :param activation_fn: Activation function
    :param normalize_images: Whether to normalize images or not,
         dividing by 255.0 (True by default)
    :param exploration_noise_scale: Standard deviation of the exploration noise at ``α = exp(log_alpha) = 1``
    """

    action_space: spaces.Box
    #: The generator's network of (state features, action, time), built by the subclass
    network: nn.Sequential
    #: ``log α`` of the entropy regulator: a buffer (saved with the policy), set and learned by the algorithm
    log_alpha: th.Tensor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: nn.Module,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        exploration_noise_scale: float = 0.15,
    ):
        super().__init__(
            observation_space,
            action_space,
            features_extractor=features_extractor,
            normalize_images=normalize_images,
            squash_output=True,
        )
        self.net_arch = net_arch
        self.features_dim = features_dim
        self.activation_fn = activation_fn
        self.action_dim = get_action_dim(self.action_space)
        self.exploration_noise_scale = exploration_noise_scale
        # log α = 0 (α = 1) until the algorithm sets it
        self.register_buffer("log_alpha", th.zeros(()))

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                net_arch=self.net_arch,
                features_dim=self.features_dim,
                activation_fn=self.activation_fn,
                features_extractor=self.features_extractor,
                exploration_noise_scale=self.exploration_noise_scale,
            )
        )
        return data

    @property
    @abstractmethod
    def noise_shape(self) -> tuple[int, ...]:
        """Shape of the noise :meth:`sample` takes for one state (without the batch dimension)."""

    @abstractmethod
    def sample(self, features: th.Tensor, noise: th.Tensor | None = None) -> th.Tensor:
        """
        Generate actions from noise, without exploration noise.

        :param features: State features ``(batch, features_dim)``
        :param noise: ``(batch, *noise_shape)``, e.g. from :meth:`draw_noise`; ``None`` for zeros (the deterministic
            action)
        :return: Actions in [-1, 1] ``(batch, action_dim)``, differentiable with respect to the network
        """

    def draw_noise(self, features: th.Tensor) -> th.Tensor:
        """
        :param features: State features ``(batch, features_dim)``, for the batch size, device and dtype
        :return: Standard normal noise ``(batch, *noise_shape)`` for :meth:`sample`
        """
        return th.randn((features.shape[0], *self.noise_shape), device=features.device, dtype=features.dtype)

    @property
    def exploration_std(self) -> th.Tensor:
        """Standard deviation of the exploration noise added to stochastic actions: ``exploration_noise_scale · α``."""
        return self.exploration_noise_scale * self.log_alpha.exp()

    def add_exploration_noise(self, actions: th.Tensor) -> th.Tensor:
        """
        :param actions: Actions in [-1, 1]
        :return: ``clip(actions + exploration_std · ξ, -1, 1)`` with ``ξ ~ N(0, I)``; ``actions`` itself when
            ``log_alpha = -inf`` (no noise drawn)
        """
        if self.log_alpha.item() == float("-inf"):
            return actions
        return (actions + self.exploration_std * th.randn_like(actions)).clamp(-1.0, 1.0)

    def act(self, features: th.Tensor, deterministic: bool = False) -> th.Tensor:
        """
        The policy's actions from state features: :meth:`forward` after the features extractor.

        :param features: State features ``(batch, features_dim)``
        :param deterministic: ``sample(features)`` (zero noise, no exploration noise) instead of sampling
        :return: Actions in [-1, 1] ``(batch, action_dim)``
        """
        if deterministic:
            return self.sample(features)
        return self.add_exploration_noise(self.sample(features, self.draw_noise(features)))

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self.act(self.extract_features(obs, self.features_extractor), deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self(observation, deterministic)

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        # Models saved by sb3_dacerf 0.1 named the network after its output: velocity_net (DACERF), noise_net (DACER)
        for legacy_name in LEGACY_NETWORK_NAMES:
            legacy_prefix = f"{prefix}{legacy_name}."
            for key in [key for key in state_dict if key.startswith(legacy_prefix)]:
                state_dict[f"{prefix}network.{key[len(legacy_prefix) :]}"] = state_dict.pop(key)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


#: Former names of :attr:`GenerativeActor.network` in saved models, renamed when they are loaded
LEGACY_NETWORK_NAMES = ("velocity_net", "noise_net")


class TwinCriticPolicy(BasePolicy):
    """
    Policy class (generative actor and twin critics) of the algorithms of this package.

    Subclasses name their actor class in ``actor_class`` and pass its own keyword arguments in ``actor_kwargs``;
    the actor samples actions in [-1, 1] when called on observations.

    :param observation_space: Observation space
    :param action_space: Action space
    :param lr_schedule: Learning rate schedule (could be constant)
    :param net_arch: The specification of the policy and value networks
        (a list for both, or ``dict(pi=[...], qf=[...])``); ``[256, 256]`` by default
    :param activation_fn: Activation function
    :param features_extractor_class: Features extractor to use.
    :param features_extractor_kwargs: Keyword arguments
        to pass to the features extractor.
    :param normalize_images: Whether to normalize images or not,
         dividing by 255.0 (True by default)
    :param optimizer_class: The optimizer to use, a class or its name (``"Adam"``, ``"AdamW"``, ``"RAD"``, ...);
        ``th.optim.Adam`` by default
    :param optimizer_kwargs: Additional keyword arguments,
        excluding the learning rate, to pass to the optimizer
    :param n_critics: Number of critic networks to create (run together, each layer of all of them one batched
        matrix product: :class:`~sb3_dacerf.common.ensemble.EnsembleCritic`)
    :param share_features_extractor: Whether to share or not the features extractor
        between the actor and the critic (this saves computation time)
    :param actor_kwargs: Keyword arguments of ``actor_class`` beyond those shared with the critics
    :param critic: The critics' networks: ``"mlp"`` (plain MLPs, SB3's critic networks: :class:`EnsembleCritic`),
        ``"layer_norm"`` (``LayerNorm`` after every hidden layer: :class:`LayerNormCritic`) or ``"batch_renorm"``
        (CrossQ's critics, batch renormalisation before every linear layer: :class:`BatchRenormCritic`, needs
        sb3-contrib; no target networks: the algorithm then bootstraps from the critics themselves, in one forward
        pass over the current and the next state-action pairs). The booleans ``critic_layer_norm`` and
        ``critic_batch_renorm`` of earlier versions are converted to it by the algorithms, with a ``FutureWarning``
    """

    actor_class: ClassVar[type[GenerativeActor]]
    actor: GenerativeActor
    critic: EnsembleCritic
    critic_target: EnsembleCritic

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] | str = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        n_critics: int = 2,
        share_features_extractor: bool = False,
        actor_kwargs: dict[str, Any] | None = None,
        critic: str = "mlp",
    ):
        if critic not in CRITICS:
            raise ValueError(f"Invalid critic={critic!r}: it must be one of {', '.join(map(repr, CRITICS))}.")
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class,
            features_extractor_kwargs,
            optimizer_class=get_optimizer_class(optimizer_class),
            optimizer_kwargs=optimizer_kwargs,
            squash_output=True,
            normalize_images=normalize_images,
        )

        if net_arch is None:
            net_arch = [256, 256]

        actor_arch, critic_arch = get_actor_critic_arch(net_arch)

        self.net_arch = net_arch
        self.activation_fn = activation_fn
        self.net_args = {
            "observation_space": self.observation_space,
            "action_space": self.action_space,
            "net_arch": actor_arch,
            "activation_fn": self.activation_fn,
            "normalize_images": normalize_images,
        }
        self.actor_kwargs = {**self.net_args, **(actor_kwargs or {})}
        self.critic_kwargs = self.net_args.copy()
        self.critic_kwargs.update(
            {
                "n_critics": n_critics,
                "net_arch": critic_arch,
                "share_features_extractor": share_features_extractor,
            }
        )
        self.share_features_extractor = share_features_extractor
        #: The ``critic`` argument (``self.critic`` is the critics' module)
        self.critic_kind = critic

        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        self.actor = self.make_actor()
        self.actor.optimizer = self.optimizer_class(
            self.actor.parameters(),
            lr=lr_schedule(1),  # type: ignore[call-arg]
            **self.optimizer_kwargs,
        )

        if self.share_features_extractor:
            self.critic = self.make_critic(features_extractor=self.actor.features_extractor)
            # The shared features extractor is trained by the actor loss only
            critic_parameters = [param for name, param in self.critic.named_parameters() if "features_extractor" not in name]
        else:
            self.critic = self.make_critic(features_extractor=None)
            critic_parameters = list(self.critic.parameters())

        # Critic target should not share the features extractor with critic
        self.critic_target = self.make_critic(features_extractor=None)
        self.critic_target.load_state_dict(self.critic.state_dict())

        self.critic.optimizer = self.optimizer_class(
            critic_parameters,
            lr=lr_schedule(1),  # type: ignore[call-arg]
            **self.optimizer_kwargs,
        )

        # Target networks should always be in eval mode
        self.critic_target.set_training_mode(False)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                net_arch=self.net_arch,
                activation_fn=self.net_args["activation_fn"],
                n_critics=self.critic_kwargs["n_critics"],
                lr_schedule=self._dummy_schedule,  # dummy lr schedule, not needed for loading policy alone
                optimizer_class=self.optimizer_class,
                optimizer_kwargs=self.optimizer_kwargs,
                features_extractor_class=self.features_extractor_class,
                features_extractor_kwargs=self.features_extractor_kwargs,
                share_features_extractor=self.share_features_extractor,
                critic=self.critic_kind,
            )
        )
        return data

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> GenerativeActor:
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return self.actor_class(**actor_kwargs).to(self.device)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> EnsembleCritic:
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        critic_classes: dict[str, type[EnsembleCritic]] = {
            "mlp": EnsembleCritic,
            "layer_norm": LayerNormCritic,
            "batch_renorm": BatchRenormCritic,
        }
        return critic_classes[self.critic_kind](**critic_kwargs).to(self.device)

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self.actor(observation, deterministic)

    def set_training_mode(self, mode: bool) -> None:
        """
        Put the policy in either training or evaluation mode.

        This affects certain modules, such as batch normalisation and dropout. Nothing is done when the actor and
        the critic are already in that mode: ``predict()`` calls this before every action, and walking all the
        sub-modules cost as much as the actor's forward pass (switch sub-modules through this method).

        :param mode: if true, set to training mode, else set to evaluation mode
        """
        if self.training == self.actor.training == self.critic.training == mode:
            return
        self.actor.set_training_mode(mode)
        self.critic.set_training_mode(mode)
        self.training = mode
