from typing import Any, ClassVar

import torch as th
from stable_baselines3.common.buffers import ReplayBuffer, ReplayBufferSamples
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import GymEnv, PyTorchObs, Schedule

from sb3_dacerf.common.policies import EnsembleCritic, twin_critic_loss
from sb3_dacerf.common.twin_critic import TwinCriticAlgorithm, frozen
from sb3_dacerf.common.validation import HyperparameterRule, integer_at_least
from sb3_dacerf.dacer.entropy import gaussian_mixture_entropy
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
    ent_coef_values = (
        "'auto' (learned from α = 3, the official code's), 'auto_<initial α > 0>' (e.g. 'auto_0.5') or a number >= 0 (fixed α)"
    )

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
