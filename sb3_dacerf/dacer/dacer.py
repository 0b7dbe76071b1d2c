from typing import Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import GymEnv, PyTorchObs, Schedule

from sb3_dacerf.common.policies import EnsembleCritic, twin_critic_loss
from sb3_dacerf.common.twin_critic import TwinCriticAlgorithm, frozen
from sb3_dacerf.common.validation import HyperparameterRule, integer_at_least, made_env
from sb3_dacerf.dacer.entropy import gaussian_mixture_entropy
from sb3_dacerf.dacer.policies import CnnPolicy, DACERPolicy, DiffusionActor, MlpPolicy, MultiInputPolicy


class DACER(TwinCriticAlgorithm):
    """
    Diffusion Actor-Critic with Entropy Regulator (DACER), the diffusion baseline of the DACER-F paper.

    A DDPM policy (``n_diffusion_steps`` reverse steps per action) trained by ``-Q(s, π(s))`` backpropagated
    through all the denoising steps; twin critics with target networks as in TD3/SAC. A diffusion policy has no
    tractable log-density, so its entropy is estimated by fitting a Gaussian mixture to ``entropy_samples``
    actions per state, every ``alpha_update_interval`` updates; the temperature ``α`` is adapted towards
    ``target_entropy`` from that estimate and only scales the exploration noise added to the actions.
    Paper: "Diffusion Actor-Critic with Entropy Regulator", Wang et al., NeurIPS 2024 (arXiv:2405.15177);
    official JAX code: https://github.com/happy-yan/DACER-Diffusion-with-Online-RL

    The defaults are the official code's (``relax/algorithm/dacer.py``, ``relax/network/dacer.py``,
    ``relax/utils/diffusion.py`` and ``scripts/train_mujoco.py`` there): learning rate 1e-4, ``α`` learned from 3
    (``log α = log 3``: ``ent_coef="auto"``) with its own learning rate 0.03, the VP noise schedule,
    ``x_T ~ N(0, I)``, 20 steps, 3 x 256 Mish networks, ``tau=0.005``, policy delay 2, α updated every 10,000 updates
    towards ``-0.9 * action_dim``.
    Differences from the official code: the critics are this package's clipped double-Q critics (shared with
    DACERF) instead of DSAC-T's distributional critics, there is no built-in reward scaling (its 0.2; use
    ``gymnasium.wrappers.TransformReward(env, lambda r: 0.2 * r)`` or ``VecNormalize``), and the mixture has
    diagonal rather than full covariances (a full 38 x 38 covariance per component is ill-determined by 200
    samples).

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, ...)
    :param env: The environment to learn from (if registered in Gym, can be str)
    :param learning_rate: learning rate for the optimizer of the actor and of the critics (1e-4, the official
        code's; SB3's SAC uses 3e-4), it can be a function of the current progress remaining (from 1 to 0)
    :param buffer_size: size of the replay buffer
    :param learning_starts: how many steps of the model to collect transitions for before learning starts
    :param batch_size: Minibatch size for each gradient update
    :param tau: the soft update coefficient ("Polyak update", between 0 and 1)
    :param gamma: the discount factor
    :param train_freq: Update the model every ``train_freq`` steps. Alternatively pass a tuple of frequency and unit
        like ``(5, "step")`` or ``(2, "episode")``.
    :param gradient_steps: How many gradient steps to do after each rollout (see ``train_freq``)
        Set to ``-1`` means to do as many gradient steps as steps done in the environment
        during the rollout.
    :param action_noise: the action noise type (None by default), added on top of the policy's own exploration
        noise during rollouts
    :param replay_buffer_class: Replay buffer class to use (for instance ``HerReplayBuffer``).
        If ``None``, it will be automatically selected.
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation.
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
        at a cost of more complexity.
    :param n_steps: When n_step > 1, uses n-step return (with the NStepReplayBuffer) when updating the Q-value network.
    :param policy_delay: Policy and target network updates happen once every ``policy_delay`` critic updates
    :param ent_coef: Entropy regulator coefficient ``α``, the exploration noise being ``N(0, (0.15 α)²)`` (as
        DACERF's): ``"auto"`` learns it starting from ``α = 3`` (the official code's ``log α = log 3``),
        ``"auto_0.5"`` starting from 0.5; a float fixes it; ``0`` adds no noise
    :param target_entropy: Target entropy of the policy; ``"auto"`` is ``-0.9 * action_dim``
    :param alpha_learning_rate: Learning rate (Adam) of ``log α`` when it is learned (the official code's 0.03; the
        actor's and critics' is ``learning_rate``), as DSAC's
    :param alpha_update_interval: The entropy is estimated and ``α`` updated once every that many updates
        (at the first update, then every ``alpha_update_interval``)
    :param entropy_samples: Number of actions sampled per state for the entropy estimate
    :param stats_window_size: Window size for the rollout logging, specifying the number of episodes to average
        the reported success rate, mean episode length, and mean reward over
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation, e.g.
        ``dict(net_arch=[256, 256], n_diffusion_steps=20, exploration_noise_scale=0.1)``:
        ``n_diffusion_steps`` is the number of reverse diffusion steps per action (20 in both papers, the default);
        see :class:`~sb3_dacerf.dacer.policies.DACERPolicy` for the others
    :param verbose: Verbosity level: 0 for no output, 1 for info messages (such as device or wrappers used), 2 for
        debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run.
        Setting it to auto, the code will be run on the GPU if possible.
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    #: DACER's own hyper-parameters with their valid values, besides those of every algorithm of the package
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
        "'auto' (learned from α = 3, the official code's), " + TwinCriticAlgorithm.ent_coef_values[len("'auto', ") :]
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
        super().__init__(
            policy,
            made_env(env, type(self).__name__, verbose),  # type: ignore[arg-type]  # SB3's load() passes env=None
            learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            action_noise=action_noise,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            supported_action_spaces=None,  # made_env() checked it, with an error that says what to do instead
            support_multi_env=True,
            sde_support=False,
        )

        # The number of steps written into a copy of policy_kwargs (the caller's dict stays reusable), so that a saved
        # model records it
        self.policy_kwargs = {"n_diffusion_steps": 20, **self.policy_kwargs}
        self.policy_delay = policy_delay
        self.ent_coef = ent_coef
        self.alpha_learning_rate = alpha_learning_rate
        self.target_entropy = target_entropy
        self.alpha_update_interval = alpha_update_interval
        self.entropy_samples = entropy_samples
        # Last entropy estimate, for the logs
        self.entropy = float("nan")

        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        super()._setup_model()
        self._setup_temperature(self.actor.log_alpha, -0.9 * float(get_action_dim(self.action_space)), self.alpha_learning_rate)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        # Switch to train mode (this affects batch norm / dropout)
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        assert self.replay_buffer is not None, "train() needs the replay buffer that _setup_model() creates"

        critic_losses, actor_losses = [], []

        for _ in range(gradient_steps):
            self._n_updates += 1
            # Replay: a batch (s, a, r, s', done), actions in [-1, 1]
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)

            # Critic update, J_Q: y = r + γ (1 - done) min_j Q̄_j(s', a'),  a' ~ π(·|s') by reverse diffusion
            with th.no_grad():
                next_actions = self.actor(replay_data.next_observations)
            critic_loss = twin_critic_loss(self.critic, self.critic_target, replay_data, next_actions, self.gamma)
            critic_losses.append(self._step(self.critic.optimizer, critic_loss, "critic loss", replay_data))

            # Actor update, every `policy_delay` critic updates: J_π = -E[min_j Q_j(s, π(s))],
            # backpropagated through all the denoising steps (the critics' parameters receive no gradient)
            if self._n_updates % self.policy_delay == 0:
                with frozen(self._critic_parameters()):
                    q_values = self.critic.q_values(replay_data.observations, self.actor(replay_data.observations))
                    actor_loss = -q_values.min(dim=0).values.mean()
                actor_losses.append(self._step(self.actor.optimizer, actor_loss, "actor loss", replay_data))

                # Target networks, with the actor as in the official code: Q̄ <- (1 - τ) Q̄ + τ Q
                self._update_targets()

            # Entropy regulator, at the first update and every `alpha_update_interval` updates (like the official
            # step counter, which starts at 0): estimate H(π(·|s)) and step log α on J(α) = -log α (H_target - H)
            if self.ent_coef_optimizer is not None and (self._n_updates - 1) % self.alpha_update_interval == 0:
                self.entropy = self._estimate_entropy(replay_data.observations)
                # ∂J(α)/∂log α = H - H_target: the noise shrinks while the policy is more random than the target
                ent_coef_loss = self.actor.log_alpha * (self.entropy - float(self.target_entropy))
                self.ent_coef_optimizer.zero_grad()
                ent_coef_loss.backward()
                self.ent_coef_optimizer.step()

        self.logger.record("train/n_updates", self._n_updates)
        self.logger.record("train/critic_loss", np.mean(critic_losses))
        if len(actor_losses) > 0:
            self.logger.record("train/actor_loss", np.mean(actor_losses))
        self.logger.record("train/ent_coef", self.actor.log_alpha.exp().item())
        self.logger.record("train/entropy", self.entropy)

    @th.no_grad()
    def _estimate_entropy(self, observations: PyTorchObs) -> float:
        """
        DACER's entropy estimate: ``entropy_samples`` actions per state (exploration noise included),
        a 3-component Gaussian mixture fitted to those of each state, its entropy averaged over the states.
        """
        features = self.actor.extract_features(observations, self.actor.features_extractor)
        actions = self.actor.act(features.repeat_interleave(self.entropy_samples, dim=0))
        return gaussian_mixture_entropy(actions.view(features.shape[0], self.entropy_samples, -1)).mean().item()
