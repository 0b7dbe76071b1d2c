import math
from typing import Any, ClassVar

import torch as th
from stable_baselines3.common.buffers import ReplayBuffer, ReplayBufferSamples
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import GymEnv, PyTorchObs, Schedule

from sb3_dacerf.common.policies import EnsembleCritic, twin_critic_loss
from sb3_dacerf.common.twin_critic import TwinCriticAlgorithm, frozen
from sb3_dacerf.common.validation import HyperparameterRule, integer_at_least
from sb3_dacerf.dacer.policies import CnnPolicy, DACERPolicy, DiffusionActor, MlpPolicy, MultiInputPolicy


class DACER(TwinCriticAlgorithm):
    """
    Diffusion Actor-Critic with Entropy Regulator (DACER), Wang et al., NeurIPS 2024 (arXiv:2405.15177), the
    diffusion baseline of the DACER-F paper; official JAX code: https://github.com/happy-yan/DACER-Diffusion-with-Online-RL

    A DDPM policy trained by ``-Q(s, π(s))`` backpropagated through all the denoising steps, twin critics with target
    networks; the temperature ``α``, adapted towards ``target_entropy`` from a Gaussian-mixture estimate of the
    policy's entropy, scales the exploration noise added to the actions. The defaults are the official code's.

    Its other arguments are those of SB3's ``SAC`` (``learning_rate``: of the actor and the critics); its own:

    :param policy_delay: Policy and target network updates happen once every ``policy_delay`` critic updates
    :param ent_coef: Entropy regulator coefficient ``α``, the exploration noise being ``N(0, (0.15 α)²)``:
        ``"auto"`` learns it from ``α = 3``, ``"auto_0.5"`` from 0.5; a float fixes it; ``0`` adds no noise
    :param target_entropy: Target entropy of the policy; ``"auto"`` is ``-0.9 * action_dim``
    :param alpha_learning_rate: Learning rate (Adam) of ``log α`` when it is learned
    :param alpha_update_interval: The entropy is estimated and ``α`` updated at the first update, then once every
        that many updates
    :param entropy_samples: Number of actions sampled per state for the entropy estimate
    :param policy_kwargs: Arguments of :class:`~sb3_dacerf.dacer.policies.DACERPolicy`, e.g.
        ``dict(net_arch=[256, 256], n_diffusion_steps=20)``
    """

    policy_aliases: ClassVar[dict] = dict(MlpPolicy=MlpPolicy, CnnPolicy=CnnPolicy, MultiInputPolicy=MultiInputPolicy)
    hyperparameter_rules: ClassVar[dict[str, HyperparameterRule]] = {
        **TwinCriticAlgorithm.hyperparameter_rules,
        "n_diffusion_steps": integer_at_least(1),  # in policy_kwargs
        "alpha_learning_rate": HyperparameterRule(lambda value: value > 0, "> 0"),
        "alpha_update_interval": integer_at_least(1),
        "entropy_samples": integer_at_least(3, "an integer >= 3 (the entropy estimate fits 3 Gaussians)"),
    }
    policy: DACERPolicy
    actor: DiffusionActor
    critic: EnsembleCritic
    critic_target: EnsembleCritic

    def __init__(
        self,
        policy: str | type[DACERPolicy],
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
        policy_delay: int = 2,
        ent_coef: str | float = "auto",
        target_entropy: str | float = "auto",
        alpha_learning_rate: float = 3e-2,
        alpha_update_interval: int = 10_000,
        entropy_samples: int = 200,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        super().__init__(locals())
        # The default written into a copy of policy_kwargs, so that a saved model records it
        self.policy_kwargs = {"n_diffusion_steps": 20, **self.policy_kwargs}
        self.alpha_learning_rate = alpha_learning_rate
        self.alpha_update_interval = alpha_update_interval
        self.entropy_samples = entropy_samples
        # Last entropy estimate, for the logs
        self.entropy = float("nan")

        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        super()._setup_model()
        self._setup_temperature(-0.9 * float(get_action_dim(self.action_space)), self.alpha_learning_rate)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        super().train(gradient_steps, batch_size)
        self.logger.record("train/entropy", self.entropy)

    def _update(self, replay_data: ReplayBufferSamples) -> dict[str, float]:
        # Critic update, J_Q: y = r + γ (1 - done) min_j Q̄_j(s', a'),  a' ~ π(·|s') by reverse diffusion
        with th.no_grad():
            next_actions = self.actor(replay_data.next_observations)
        critic_loss = twin_critic_loss(self.critic, self.critic_target, replay_data, next_actions, self.gamma)
        logs = {"critic_loss": self._step(self.critic.optimizer, critic_loss, "critic loss", replay_data)}

        # Actor update, every `policy_delay` critic updates: J_π = -E[min_j Q_j(s, π(s))], backpropagated through all
        # the denoising steps; then the target networks, with the actor as in the official code
        if self._n_updates % self.policy_delay == 0:
            with frozen(self._critic_parameters()):
                q_values = self.critic.q_values(replay_data.observations, self.actor(replay_data.observations))
                actor_loss = -q_values.min(dim=0).values.mean()
            logs["actor_loss"] = self._step(self.actor.optimizer, actor_loss, "actor loss", replay_data)
            self._update_targets()

        # Entropy regulator, at the first update and every `alpha_update_interval` updates (as the official step
        # counter, which starts at 0)
        if self.ent_coef_optimizer is not None and (self._n_updates - 1) % self.alpha_update_interval == 0:
            self.entropy = self._estimate_entropy(replay_data.observations)
            self._update_temperature(self.entropy)
        return logs

    @th.no_grad()
    def _estimate_entropy(self, observations: PyTorchObs) -> float:
        """DACER's entropy estimate: a 3-component Gaussian mixture fitted to ``entropy_samples`` actions (exploration
        noise included) of each state, its entropy averaged over the states."""
        features = self.actor.extract_features(observations, self.actor.features_extractor)
        actions = self.actor.act(features.repeat_interleave(self.entropy_samples, dim=0))
        return gaussian_mixture_entropy(actions.view(features.shape[0], self.entropy_samples, -1)).mean().item()


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
