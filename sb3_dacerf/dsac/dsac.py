import functools
import math
import operator
from collections.abc import Sequence
from typing import Any, ClassVar

import torch as th
from stable_baselines3.common.buffers import ReplayBuffer, ReplayBufferSamples
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from stable_baselines3.common.utils import polyak_update
from torch.nn import functional as F

from sb3_dacerf.common.twin_critic import TwinCriticAlgorithm, frozen
from sb3_dacerf.common.validation import HyperparameterRule
from sb3_dacerf.dsac.policies import CnnPolicy, DSACPolicy, GaussianActor, GaussianCritic, MlpPolicy, MultiInputPolicy

# The constants of DSAC-T's critic loss, as in the authors' code
STD_EPSILON = 0.1  # ε of the weighting of the mean and standard-deviation gradients
WEIGHT_RANGE = (0.1, 10.0)  # range of the weight ω̄² / (σ² + ε)
HUBER_DELTA = 50.0  # δ of the Huber losses
TARGET_BOUND_SCALE = 3.0  # y_z - Q is bounded to ±TARGET_BOUND_SCALE ω̄
SAMPLE_CLIP = 3.0  # clip of the standard normal z of a sampled return Q̄ + z σ̄


def distributional_targets(
    rewards: th.Tensor,
    discounts: th.Tensor | float,
    next_distributions: Sequence[tuple[th.Tensor, th.Tensor]],
    next_log_prob: th.Tensor,
    ent_coef: float,
    normals: Sequence[th.Tensor],
) -> tuple[th.Tensor, th.Tensor]:
    """
    DSAC-T's targets from the target critics' ``(Q̄_j, σ̄_j)`` at ``(s', a')`` (``next_distributions``), ``j*`` the
    critic of the smaller mean, ``γ' = γ (1 - done)`` (``discounts``), ``z_j`` the ``normals``, all ``(batch, 1)``:
    ``y = r + γ' (Q̄_j* - α log π̄(a'|s'))`` and ``y_z = r + γ' (Q̄_j* + clip(z_j*, -3, 3) σ̄_j* - α log π̄(a'|s'))``.
    """
    (mean_1, std_1), (mean_2, std_2) = next_distributions
    sample_1 = mean_1 + normals[0].clamp(-SAMPLE_CLIP, SAMPLE_CLIP) * std_1
    sample_2 = mean_2 + normals[1].clamp(-SAMPLE_CLIP, SAMPLE_CLIP) * std_2
    next_mean = th.min(mean_1, mean_2)
    next_sample = th.where(mean_1 < mean_2, sample_1, sample_2)
    entropy_bonus = -ent_coef * next_log_prob
    return rewards + discounts * (next_mean + entropy_bonus), rewards + discounts * (next_sample + entropy_bonus)


def bounded_target(current_mean: th.Tensor, target_sample: th.Tensor, running_std: float | th.Tensor) -> th.Tensor:
    """DSAC-T's bounded sampled target ``y_b = Q + clip(y_z - Q, -3 ω̄, 3 ω̄)``, without gradient, from the critic's
    mean ``Q``, the sampled target ``y_z`` and the running mean ``ω̄`` of the critic's standard deviation."""
    current_mean = current_mean.detach()
    bound = TARGET_BOUND_SCALE * th.as_tensor(running_std, dtype=current_mean.dtype, device=current_mean.device)
    return (current_mean + th.clamp(target_sample.detach() - current_mean, -bound, bound)).detach()


def critic_loss(
    mean: th.Tensor, std: th.Tensor, target_mean: th.Tensor, target_bound: th.Tensor, running_std: float | th.Tensor
) -> th.Tensor:
    """
    The loss of one Gaussian critic ``N(Q, σ²)`` (``mean``, ``std``), whose gradients are DSAC-T's: the mean follows
    the target ``y`` (``target_mean``), the standard deviation the bounded sampled target ``y_b`` (``target_bound``):
    ``mean(w (huber_δ(Q, y) + σ (σ_d² - huber_δ(Q_d, y_b)) / (σ_d + ε)))``, ``w = clip(ω̄² / (σ_d² + ε), 0.1, 10)``,
    ``δ = 50``, ``ω̄`` the running mean of ``σ`` (``running_std``), ``_d`` treated as a constant. Only its gradients
    are meaningful: ``∂/∂Q = w (Q - y)``, ``∂/∂σ = w (σ² - (Q - y_b)²/2) / (σ + ε)`` per sample.
    """
    omega = th.as_tensor(running_std, dtype=mean.dtype, device=mean.device)
    std_d = th.clamp(std, min=0.0).detach()
    mean_d = mean.detach()
    target_mean, target_bound = target_mean.detach(), target_bound.detach()
    weight = (omega.pow(2) / (std_d.pow(2) + STD_EPSILON)).clamp(*WEIGHT_RANGE)
    mean_term = F.huber_loss(mean, target_mean, delta=HUBER_DELTA, reduction="none")
    std_term = std * (std_d.pow(2) - F.huber_loss(mean_d, target_bound, delta=HUBER_DELTA, reduction="none"))
    return th.mean(weight * (mean_term + std_term / (std_d + STD_EPSILON)))


def updated_running_std(running_std: list[float] | None, stds: Sequence[th.Tensor], tau_b: float) -> list[float]:
    """The running means ``ω̄_i <- (1 - tau_b) ω̄_i + tau_b mean(σ_i)`` of the critics' standard deviations ``stds``
    (``ω̄_i`` starts at the first batch's mean: ``running_std`` ``None``)."""
    batch_stds = [std.detach().mean().item() for std in stds]
    if running_std is None:
        return batch_stds
    return [(1 - tau_b) * old + tau_b * new for old, new in zip(running_std, batch_stds, strict=True)]


def gaussian_critics_loss(
    distributions: Sequence[tuple[th.Tensor, th.Tensor]],
    target_mean: th.Tensor,
    target_sample: th.Tensor,
    running_std: Sequence[float],
) -> th.Tensor:
    """The sum over the critics' ``(Q_i, σ_i)`` ``distributions`` of :func:`critic_loss`, each critic's sampled target
    bounded by its running standard deviation ``ω̄_i`` (:func:`bounded_target`)."""
    losses = [
        critic_loss(mean, std, target_mean, bounded_target(mean, target_sample, omega), omega)
        for (mean, std), omega in zip(distributions, running_std, strict=True)
    ]
    return functools.reduce(operator.add, losses)


class DSAC(TwinCriticAlgorithm):
    """
    Distributional Soft Actor-Critic with three refinements (DSAC-T, also called DSAC v2), the Gaussian-policy
    baseline of the DACER-F paper: Duan et al., IEEE TPAMI 2025 (arXiv:2310.05858); authors' code:
    https://github.com/Jingliang-Duan/DSAC-v2 (``dsac_v2.py``).

    Twin critics of Gaussian returns ``N(Q_i, σ_i²)``, each mean regressed on the expected-value target and each
    standard deviation on a bounded sampled one (:func:`distributional_targets`, :func:`critic_loss`), ``a'`` from a
    target policy; a tanh-Gaussian actor and temperature ``α`` trained as SAC's, with target networks, every
    ``policy_delay`` critic updates. The defaults are the authors'.

    Its other arguments are those of SB3's ``SAC`` (``learning_rate``: of the actor and the critics; ``tau``: of the
    target critics and policy); its own:

    :param ent_coef: Entropy temperature ``α``: ``"auto"`` learns it from ``α = e`` (``log α = 1``, the authors'
        start), ``"auto_<x>"`` from ``α = x > 0`` (``"auto_1"`` is SB3's SAC), a number ``>= 0`` keeps it fixed
    :param target_entropy: Target entropy when ``α`` is learned; ``"auto"`` is ``-dim(A)``
    :param alpha_learning_rate: Learning rate (Adam) of ``log α``
    :param policy_delay: The actor, ``α`` and the target networks are updated at the first update, then once every
        ``policy_delay`` critic updates
    :param tau_b: Coefficient of the running mean ``ω̄`` of each critic's standard deviation,
        ``ω̄ <- (1 - tau_b) ω̄ + tau_b mean(σ)`` (``ω̄`` starts at the first batch's mean); ``None``: ``tau``
    :param policy_kwargs: Arguments of :class:`~sb3_dacerf.dsac.policies.DSACPolicy`, e.g.
        ``dict(net_arch=[256, 256], activation_fn=nn.ReLU, log_std_max=2)``
    """

    policy_aliases: ClassVar[dict] = dict(MlpPolicy=MlpPolicy, CnnPolicy=CnnPolicy, MultiInputPolicy=MultiInputPolicy)
    hyperparameter_rules: ClassVar[dict[str, HyperparameterRule]] = {
        **TwinCriticAlgorithm.hyperparameter_rules,
        "alpha_learning_rate": HyperparameterRule(lambda value: value > 0, "> 0"),
        "tau_b": HyperparameterRule(lambda value: 0 < value <= 1, "in (0, 1], or None for tau"),
    }
    policy: DSACPolicy
    actor: GaussianActor
    actor_target: GaussianActor
    critic: GaussianCritic
    critic_target: GaussianCritic
    auto_ent_coef = math.e  # log α = 1, as the authors' code (SB3's SAC starts at α = 1)

    def __init__(
        self,
        policy: str | type[DSACPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-4,
        buffer_size: int = 1_000_000,  # 1e6
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        ent_coef: str | float = "auto",
        target_entropy: str | float = "auto",
        alpha_learning_rate: float = 3e-4,
        policy_delay: int = 2,
        tau_b: float | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        super().__init__(locals())
        self.alpha_learning_rate = alpha_learning_rate
        self.tau_b = tau if tau_b is None else tau_b
        self.running_std = None

        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        #: log α, trained by its own loss and optimizer when α is learned (as SB3's SAC)
        self.log_ent_coef = th.zeros((), device=self.device)
        super()._setup_model()
        self._setup_temperature(-float(get_action_dim(self.action_space)), self.alpha_learning_rate)

    @property
    def log_alpha(self) -> th.Tensor:
        """``log α``, the temperature: ``log_ent_coef``."""
        return self.log_ent_coef

    def _create_aliases(self) -> None:
        super()._create_aliases()
        self.actor_target = self.policy.actor_target

    def _update(self, replay_data: ReplayBufferSamples) -> dict[str, float]:
        """The critics' step, and every ``policy_delay`` updates the actor's, ``α``'s and the targets', all gradients
        computed before any step, as in the authors' code."""
        # The actor, α and the targets move at the first update, then every `policy_delay` (the authors' counter from 0)
        update_actor = (self._n_updates - 1) % self.policy_delay == 0
        # For n-step replay, discount factor is gamma**n_steps (when no early termination)
        discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
        ent_coef = self.log_ent_coef.exp().item()

        with th.no_grad():
            # a' ~ π̄(·|s') from the target policy; both target critics' distributions at (s', a')
            next_actions, next_log_prob = self.actor_target.action_log_prob(replay_data.next_observations)
            next_distributions = self.critic_target.distributions(replay_data.next_observations, next_actions)
            target_mean, target_sample = distributional_targets(
                replay_data.rewards,
                (1 - replay_data.dones) * discounts,
                next_distributions,
                next_log_prob.reshape(-1, 1),
                ent_coef,
                [th.randn_like(mean) for mean, _ in next_distributions],
            )

        distributions = self.critic.distributions(replay_data.observations, replay_data.actions)
        self.running_std = updated_running_std(self.running_std, [std for _, std in distributions], self.tau_b)
        loss = gaussian_critics_loss(distributions, target_mean, target_sample, self.running_std)
        logs = {"critic_loss": self._checked(loss, "critic loss", replay_data)}
        for index, (mean, std) in enumerate(distributions, start=1):
            logs[f"q{index}_mean"] = mean.detach().mean().item()
            logs[f"q{index}_std"] = std.detach().mean().item()

        self.critic.optimizer.zero_grad()
        loss.backward()

        if update_actor:
            # J_π = E[α log π(a|s) - min_j Q_j(s, a)], a ~ π(·|s) reparameterised; the critics receive no gradient
            actions, log_prob = self.actor.action_log_prob(replay_data.observations)
            with frozen(self._critic_parameters()):
                min_q = th.min(th.cat(self.critic(replay_data.observations, actions), dim=1), dim=1, keepdim=True).values
                actor_loss = (ent_coef * log_prob.reshape(-1, 1) - min_q).mean()
            logs["actor_loss"] = self._checked(actor_loss, "actor loss", replay_data)
            logs["entropy"] = -log_prob.detach().mean().item()
            self.actor.optimizer.zero_grad()
            actor_loss.backward()

        self.critic.optimizer.step()
        if update_actor:
            self.actor.optimizer.step()
            if self.ent_coef_optimizer is not None:
                logs["ent_coef_loss"] = self._update_temperature(logs["entropy"])
            self._update_targets()
        return logs

    def _update_targets(self) -> None:
        """Polyak update of the target critics and of the target policy: ``θ̄ <- (1 - τ) θ̄ + τ θ``."""
        super()._update_targets()
        polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "actor_target"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, saved_variables = super()._get_torch_save_params()
        return state_dicts, [*saved_variables, "log_ent_coef"]
