"""The policies' parts: the actor bases, the ensemble critics and the twin-critic policy that holds them."""

import functools
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBufferSamples
from stable_baselines3.common.policies import BaseModel, BasePolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, FlattenExtractor, create_mlp, get_actor_critic_arch
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn
from torch.nn import functional as F

from sb3_dacerf.common.optim import get_optimizer_class

#: The critics of :class:`TwinCriticPolicy` (its ``critic`` argument)
CRITICS = ("mlp", "layer_norm", "batch_renorm")


class Actor(BasePolicy, ABC):
    """
    Base of the actors: :meth:`sample` maps state features and noise to actions in [-1, 1], differentiably in the
    network (``noise=None``, the noise's mean: the deterministic action); :meth:`act` and ``forward`` add
    :meth:`add_exploration_noise` to stochastic actions. Takes the arguments of SB3's SAC ``Actor`` but gSDE's.
    """

    action_space: spaces.Box
    #: The network of the state features, built by the subclass
    network: nn.Sequential
    #: The subclass's own constructor arguments, saved with the actor from the attributes of their names
    own_arguments: ClassVar[tuple[str, ...]] = ()

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: nn.Module,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
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

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            net_arch=self.net_arch,
            features_dim=self.features_dim,
            activation_fn=self.activation_fn,
            features_extractor=self.features_extractor,
            **{name: getattr(self, name) for name in self.own_arguments},
        )
        return data

    @property
    @abstractmethod
    def noise_shape(self) -> tuple[int, ...]:
        """Shape of the noise :meth:`sample` takes for one state (without the batch dimension)."""

    @abstractmethod
    def sample(self, features: th.Tensor, noise: th.Tensor | None = None) -> th.Tensor:
        """Actions in [-1, 1] ``(batch, action_dim)`` from state features and noise ``(batch, *noise_shape)``."""

    def draw_noise(self, features: th.Tensor) -> th.Tensor:
        """Standard normal noise ``(batch, *noise_shape)`` for :meth:`sample`, on the device and dtype of ``features``."""
        return th.randn((features.shape[0], *self.noise_shape), device=features.device, dtype=features.dtype)

    def add_exploration_noise(self, actions: th.Tensor) -> th.Tensor:
        """Exploration added to stochastic actions: none here."""
        return actions

    def act(self, features: th.Tensor, deterministic: bool = False) -> th.Tensor:
        """:meth:`forward` from state features ``(batch, features_dim)``: actions in [-1, 1] ``(batch, action_dim)``."""
        if deterministic:
            return self.sample(features)
        return self.add_exploration_noise(self.sample(features, self.draw_noise(features)))

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self.act(self.extract_features(obs, self.features_extractor), deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self(observation, deterministic)


class GenerativeActor(Actor):
    """
    Base of the generative actors (DACER-F's, DACER's): a network of (state features, action, time), and exploration
    noise ``clip(a + exploration_noise_scale · α · ξ, -1, 1)``, ``ξ ~ N(0, I)``, on stochastic actions, with the
    temperature ``α = exp(log_alpha)`` that the algorithm sets and learns. Takes the arguments of :class:`Actor`.
    """

    #: Standard deviation of the exploration noise at ``α = 1``
    exploration_noise_scale: ClassVar[float] = 0.15
    #: ``log α`` of the entropy regulator, saved with the actor; the algorithm sets it and trains it with its own optimizer
    log_alpha: nn.Parameter

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.log_alpha = nn.Parameter(th.zeros(()), requires_grad=False)

    @property
    def exploration_std(self) -> th.Tensor:
        """Standard deviation of the exploration noise: ``exploration_noise_scale · α``."""
        return self.exploration_noise_scale * self.log_alpha.exp()

    def add_exploration_noise(self, actions: th.Tensor) -> th.Tensor:
        """``clip(actions + exploration_std · ξ, -1, 1)``; ``actions`` itself (no draw) when ``log_alpha = -inf``."""
        if self.log_alpha.item() == float("-inf"):
            return actions
        return (actions + self.exploration_std * th.randn_like(actions)).clamp(-1.0, 1.0)


class EnsembleLinear(nn.Module):
    """Copies of the ``linears`` (with biases, of one shape) in one batched product: ``y[j] = x[j] @ weight[j] + bias[j]``."""

    def __init__(self, linears: list[nn.Linear]):
        super().__init__()
        self.n_members, self.in_features, self.out_features = len(linears), linears[0].in_features, linears[0].out_features
        #: ``(n_members, in_features, out_features)``: member ``j`` computes ``x @ weight[j]``
        self.weight = nn.Parameter(th.stack([linear.weight.detach().t() for linear in linears]))
        #: ``(n_members, out_features)``
        self.bias = nn.Parameter(th.stack([linear.bias.detach() for linear in linears]))

    def forward(self, x: th.Tensor) -> th.Tensor:
        """``(n_members, batch, out_features)`` from ``(batch, in_features)`` or ``(n_members, batch, in_features)``."""
        if x.dim() == 2:
            x = x.expand(self.n_members, *x.shape)
        return th.baddbmm(self.bias.unsqueeze(1), x, self.weight)

    def extra_repr(self) -> str:
        return f"n_members={self.n_members}, in_features={self.in_features}, out_features={self.out_features}"


class EnsembleLayerNorm(nn.Module):
    """``LayerNorm`` of ``num_features`` over the last dimension, with an affine transform per member (critic)."""

    def __init__(self, n_members: int, num_features: int, eps: float = 1e-5):
        super().__init__()
        self.n_members, self.num_features, self.eps = n_members, num_features, eps
        self.weight = nn.Parameter(th.ones(n_members, num_features))
        self.bias = nn.Parameter(th.zeros(n_members, num_features))

    def forward(self, x: th.Tensor) -> th.Tensor:
        """:param x: ``(n_members, batch, num_features)``"""
        normalised = F.layer_norm(x, (self.num_features,), eps=self.eps)
        return th.addcmul(self.bias.unsqueeze(1), normalised, self.weight.unsqueeze(1))

    def extra_repr(self) -> str:
        return f"n_members={self.n_members}, num_features={self.num_features}, eps={self.eps}"


class EnsembleBatchRenorm(nn.Module):
    """Batch renormalisation (Ioffe 2017) with running statistics and an affine transform per member: sb3-contrib's
    ``BatchRenorm1d`` (CrossQ's, the same arguments) member by member."""

    ra_mean: th.Tensor
    ra_var: th.Tensor
    steps: th.Tensor

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

    def normalisation(self) -> tuple[th.Tensor, th.Tensor]:
        """The affine map of evaluation mode, ``x -> gain * x + shift``: ``gain``, ``shift``, ``(n_members, num_features)``."""
        gain = self.scale / (self.ra_var + self.eps).sqrt()
        return gain, self.bias - gain * self.ra_mean

    def forward(self, x: th.Tensor) -> th.Tensor:
        """``(n_members, batch, num_features)`` from ``(batch, num_features)`` or ``(n_members, batch, num_features)``."""
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
        return f"n_members={self.n_members}, num_features={self.num_features}, momentum={self.momentum}"


def ensemble_of(modules: list[nn.Module]) -> nn.Module:
    """The ensemble layer of one layer of each member: :class:`EnsembleLinear` of ``nn.Linear`` layers, else the first
    module (an ensemble normalisation layer, built for all the members, or an activation)."""
    first = modules[0]
    if type(first) is nn.Linear:
        return EnsembleLinear(modules)  # type: ignore[arg-type]
    if not isinstance(first, (EnsembleLayerNorm, EnsembleBatchRenorm)) and [*first.parameters(), *first.buffers()]:
        raise ValueError(f"No ensemble version of {type(first).__name__}: critics are built of Linear layers and activations")
    return first


class EnsembleCritic(BaseModel):
    """
    ``n_critics`` Q-networks ``Q_j(s, a) = MLP_j(concat(features(s), a))`` run as one network (:attr:`ensemble`).
    Same arguments as SB3's ``ContinuousCritic``; calling it returns one ``(batch, 1)`` tensor per critic as that
    does, :meth:`q_values` returns them stacked. And:

    :param distributional: Each network also outputs the standard deviation of a Gaussian return whose mean is
        ``Q_j`` (DSAC's critics, :meth:`distributions`)
    """

    features_extractor: BaseFeaturesExtractor
    #: Ensemble normalisation layers before and after each linear layer (``create_mlp``'s arguments of these names)
    pre_linear_modules: ClassVar[tuple[type[nn.Module], ...]] = ()
    post_linear_modules: ClassVar[tuple[type[nn.Module], ...]] = ()

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
        distributional: bool = False,
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        self.share_features_extractor = share_features_extractor
        self.n_critics = n_critics
        self.distributional = distributional
        input_dim = features_dim + get_action_dim(action_space)
        # Each member network as create_mlp builds it (the same random draws), its normalisation layers already ensemble
        # layers of all the members (ensemble_of keeps the first member's)
        normalisation: dict[str, Any] = {
            name: [functools.partial(module, n_critics) for module in getattr(self, name)]
            for name in ("pre_linear_modules", "post_linear_modules")
        }
        n_outputs = 2 if distributional else 1  # a distributional critic's second output is its standard deviation's
        members = [
            nn.Sequential(*create_mlp(input_dim, n_outputs, net_arch, activation_fn, **normalisation)) for _ in range(n_critics)
        ]
        self.ensemble = nn.Sequential(*[ensemble_of(list(layers)) for layers in zip(*members, strict=True)])

    def q_values_of_features(self, features: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """Every critic's ``Q_j(s, a)`` ``(n_critics, batch, 1)`` from the state features (a distributional
        critic's mean)."""
        return self.ensemble(th.cat([features, actions], dim=1))[..., :1]

    def distributions(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """A distributional critic's means ``Q_j(s, a)`` and standard deviations ``σ_j(s, a) = softplus(·)`` of its
        Gaussian returns, each ``(n_critics, batch, 1)``."""
        with th.set_grad_enabled(not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        outputs = self.ensemble(th.cat([features, actions], dim=1))
        return outputs[..., :1], F.softplus(outputs[..., 1:])

    def q_values(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """Every critic's ``Q_j(s, a)``, ``(n_critics, batch, 1)`` (no gradient to a features extractor shared with the actor)."""
        with th.set_grad_enabled(not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        return self.q_values_of_features(features, actions)

    def forward(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        return tuple(self.q_values(obs, actions).unbind(0))


class LayerNormCritic(EnsembleCritic):
    """:class:`EnsembleCritic` with ``LayerNorm`` after every hidden linear layer (before the activation), as BRO's."""

    post_linear_modules = (EnsembleLayerNorm,)


class BatchRenormCritic(EnsembleCritic):
    """
    :class:`EnsembleCritic` with CrossQ's batch renormalisation before every linear layer, normalising with the
    running statistics except while :meth:`set_bn_training_mode` is on (the critic loss's joint pass over
    ``(s, a)`` and ``(s', a')``).
    """

    pre_linear_modules = (EnsembleBatchRenorm,)

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.set_bn_training_mode(False)

    def set_training_mode(self, mode: bool) -> None:
        super().set_training_mode(mode)
        # The normalisation layers leave running-statistics mode only through set_bn_training_mode
        self.set_bn_training_mode(False)

    def set_bn_training_mode(self, mode: bool) -> None:
        """:param mode: ``True``: normalise with the batch's statistics, updating the running ones; ``False``: with the latter"""
        for module in self.modules():
            if isinstance(module, EnsembleBatchRenorm):
                module.train(mode)


def twin_critic_loss(
    critic: EnsembleCritic, critic_target: EnsembleCritic, replay_data: ReplayBufferSamples, next_actions: th.Tensor, gamma: float
) -> th.Tensor:
    """
    The critic loss ``J_Q = 0.5 Σ_i mean((y - Q_i(s, a))²)`` of the critics ``Q_i`` on a replay batch, with the
    Bellman target ``y = r + γ (1 - done) min_j Q̄_j(s', a')`` of the targets ``Q̄_j`` (of the critics themselves with
    CrossQ's critics, whose running statistics this pass updates), ``a'`` the ``next_actions``, ``γ`` the
    ``replay_data.discounts`` of n-step returns or else ``gamma``.
    """
    discounts = replay_data.discounts if replay_data.discounts is not None else gamma
    if isinstance(critic, BatchRenormCritic):
        # One pass over (s, a) and (s', a'), so that the batch statistics are those of both, in training mode for it only
        critic.set_bn_training_mode(True)
        try:
            all_q_values = critic.q_values(
                _cat_observations(replay_data.observations, replay_data.next_observations),
                th.cat([replay_data.actions, next_actions], dim=0),
            )
        finally:  # back to the running statistics even if the pass fails, so no later pass updates them
            critic.set_bn_training_mode(False)
        current_q_values, next_q_values = th.split(all_q_values, replay_data.actions.shape[0], dim=1)
        next_q_values = next_q_values.detach()
    else:
        with th.no_grad():
            next_q_values = critic_target.q_values(replay_data.next_observations, next_actions)
        current_q_values = critic.q_values(replay_data.observations, replay_data.actions)
    with th.no_grad():
        # (n_critics, batch, 1) -> (batch, 1)
        target_q_values = replay_data.rewards + (1 - replay_data.dones) * discounts * next_q_values.min(dim=0).values
    # 0.5 * sum_j mean((Q_j - y)^2): every critic's MSE, from the stacked Q-values in one pass
    return 0.5 * (current_q_values - target_q_values).pow(2).mean(dim=(1, 2)).sum()


def _cat_observations(first: PyTorchObs, second: PyTorchObs) -> PyTorchObs:
    """Two batches of observations (tensors, or dicts of tensors) as one."""
    if isinstance(first, dict) and isinstance(second, dict):
        return {key: th.cat([first[key], second[key]], dim=0) for key in first}
    return th.cat([first, second], dim=0)  # type: ignore[list-item]


class TwinCriticPolicy(BasePolicy):
    """
    Policy class (an actor, twin critics and their targets) of the algorithms of this package: subclasses name their
    actor class in ``actor_class`` and pass its own keyword arguments in ``actor_kwargs``.

    Takes the arguments of SB3's ``SACPolicy`` but those of gSDE (``None`` for ``net_arch``, ``activation_fn`` and
    ``features_extractor_class``: the class attributes ``default_*``; ``optimizer_class`` a class or its name:
    ``"Adam"``, ``"AdamW"``, ``"RAD"``, ...), and:

    :param actor_kwargs: Keyword arguments of ``actor_class`` beyond those shared with the critics
    :param critic: The critics' networks: ``"mlp"`` (SB3's MLPs: :class:`EnsembleCritic`), ``"layer_norm"``
        (:class:`LayerNormCritic`) or ``"batch_renorm"`` (CrossQ's critics: :class:`BatchRenormCritic`, without
        target networks: the algorithm bootstraps from the critics themselves)
    """

    actor_class: ClassVar[type[Actor]]
    default_features_extractor_class: ClassVar[type[BaseFeaturesExtractor]] = FlattenExtractor
    default_net_arch: ClassVar[tuple[int, ...]] = (256, 256)
    default_activation_fn: ClassVar[type[nn.Module]] = nn.ReLU
    critic_classes: ClassVar[dict[str, type[EnsembleCritic]]] = {
        "mlp": EnsembleCritic,
        "layer_norm": LayerNormCritic,
        "batch_renorm": BatchRenormCritic,
    }
    actor: Actor
    critic: BaseModel
    critic_target: BaseModel

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        *,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] | None = None,
        features_extractor_class: type[BaseFeaturesExtractor] | None = None,
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
            features_extractor_class or self.default_features_extractor_class,
            features_extractor_kwargs,
            optimizer_class=get_optimizer_class(optimizer_class),
            optimizer_kwargs=optimizer_kwargs,
            squash_output=True,
            normalize_images=normalize_images,
        )
        self.net_arch = list(self.default_net_arch) if net_arch is None else net_arch
        self.activation_fn = activation_fn = activation_fn or self.default_activation_fn
        self.share_features_extractor = share_features_extractor
        #: The ``critic`` argument (``self.critic`` is the critics' module)
        self.critic_kind = critic
        #: ``actor_kwargs``, saved with the policy's other arguments
        self.actor_options = actor_kwargs or {}
        actor_arch, critic_arch = get_actor_critic_arch(self.net_arch)
        shared = dict(observation_space=self.observation_space, action_space=self.action_space, normalize_images=normalize_images)
        self.actor_kwargs = {**shared, "activation_fn": activation_fn, "net_arch": actor_arch, **self.actor_options}
        self.critic_kwargs = {**shared, "activation_fn": activation_fn, "net_arch": critic_arch, "n_critics": n_critics}
        self.critic_kwargs.update(share_features_extractor=share_features_extractor)
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        optimizer_kwargs = dict(lr=lr_schedule(1), **self.optimizer_kwargs)
        self.actor = self.make_actor()
        # The temperature log α, a parameter of generative actors, has the algorithm's optimizer
        actor_parameters = [param for name, param in self.actor.named_parameters() if name != "log_alpha"]
        self.actor.optimizer = self.optimizer_class(actor_parameters, **optimizer_kwargs)
        if self.share_features_extractor:
            self.critic = self.make_critic(features_extractor=self.actor.features_extractor)
            # The shared features extractor is trained by the actor loss only
            critic_parameters = [param for name, param in self.critic.named_parameters() if "features_extractor" not in name]
        else:
            self.critic = self.make_critic(features_extractor=None)
            critic_parameters = list(self.critic.parameters())
        # The target critics have a features extractor of their own, and stay in evaluation mode
        self.critic_target = self.make_critic(features_extractor=None)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.critic.optimizer = self.optimizer_class(critic_parameters, **optimizer_kwargs)
        self.critic_target.set_training_mode(False)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            n_critics=self.critic_kwargs["n_critics"],
            lr_schedule=self._dummy_schedule,  # dummy lr schedule, not needed for loading policy alone
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
            features_extractor_class=self.features_extractor_class,
            features_extractor_kwargs=self.features_extractor_kwargs,
            share_features_extractor=self.share_features_extractor,
            critic=self.critic_kind,
            **self.actor_options,
        )
        return data

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> Actor:
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return self.actor_class(**actor_kwargs).to(self.device)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> BaseModel:
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return self.critic_classes[self.critic_kind](**critic_kwargs).to(self.device)

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self.actor(observation, deterministic)

    def set_training_mode(self, mode: bool) -> None:
        """Put the policy in training or evaluation mode; nothing to do if already in it (``predict()`` calls this often)."""
        if self.training == self.actor.training == self.critic.training == mode:
            return
        self.actor.set_training_mode(mode)
        self.critic.set_training_mode(mode)
        self.training = mode
