from typing import Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, PyTorchObs, Schedule
from torch.nn import functional as F

from sb3_dacerf.common.langevin import MinQActionGradient, compiled_langevin_targets, langevin_targets
from sb3_dacerf.common.twin_critic import TwinCriticAlgorithm
from sb3_dacerf.common.utils import frozen
from sb3_dacerf.dacerf.policies import CnnPolicy, DACERFPolicy, MlpPolicy, MultiInputPolicy, VelocityField


class DACERF(TwinCriticAlgorithm):
    """
    Diffusion Actor-Critic with Entropy Regulator via Flow matching (DACER-F).

    A flow-matching policy that generates an action in one Euler step, trained towards targets ``a*``
    obtained by Langevin dynamics on the critic (``p(a|s) ∝ exp(Q(s, a) / α)``) started from replay actions,
    plus the usual ``-Q(s, π(s))`` improvement term; twin critics with target networks as in TD3/SAC.
    Paper: "DACER-F: Langevin-guided flow matching for real-time autonomous driving", arXiv:2603.02613.

    The actor loss is ``J_F = -Q(s, π(s)) + λ_f ||v(s, a_t, t) - (a* - a_0)||²`` with the per-sample weight
    ``λ_f = flow_matching_coef * mean|Q(s, π(s))| * g / mean(g)``, ``g = ReLU(Q(s, a*) - Q(s, a_B))``:
    the paper's advantage weighting ``λ_f ∝ ReLU(Q(s, a*) - Q(s, a_B))``, normalised by its batch mean and
    by the Q scale so that the balance of the two terms does not drift with the reward scale.
    Every Q above is ``min(Q_1, Q_2)``, the same pessimistic estimate as in the Bellman target.

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, ...)
    :param env: The environment to learn from (if registered in Gym, can be str)
    :param learning_rate: learning rate for the optimizer of the actor and of the critics,
        it can be a function of the current progress remaining (from 1 to 0)
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
    :param action_noise: the action noise type (None by default), added to the flow policy's own samples
        during rollouts (extra exploration, see the README's "Exploration" section)
    :param replay_buffer_class: Replay buffer class to use (for instance ``HerReplayBuffer``).
        If ``None``, it will be automatically selected.
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation.
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
        at a cost of more complexity.
    :param n_steps: When n_step > 1, uses n-step return (with the NStepReplayBuffer) when updating the Q-value network.
    :param policy_delay: The actor is updated once every ``policy_delay`` critic updates
    :param langevin_steps: Number of Langevin steps ``N_l`` that turn replay actions into targets ``a*``
    :param langevin_step_size: Langevin step size ``η_a``
    :param langevin_temperature: Temperature ``α`` of the energy-based target ``exp(Q / α)``
    :param n_sampling_steps: Number of Euler steps of the flow sampler (1 in the paper: one network call per action)
    :param flow_matching_coef: Weight of the flow-matching (imitation) term relative to the ``-Q`` term
    :param compile_langevin: Run the Langevin loop through ``torch.compile`` (same targets; the first update
        compiles for ~30 s on a CPU, then the loop is faster: see benchmarks/iteration_time.py)
    :param stats_window_size: Window size for the rollout logging, specifying the number of episodes to average
        the reported success rate, mean episode length, and mean reward over
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation, e.g.
        ``dict(net_arch=[256, 256], optimizer_class="RAD", optimizer_kwargs=dict(zeta=1e-16))``
    :param verbose: Verbosity level: 0 for no output, 1 for info messages (such as device or wrappers used), 2 for
        debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run.
        Setting it to auto, the code will be run on the GPU if possible.
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    policy: DACERFPolicy
    actor: VelocityField
    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }

    def __init__(
        self,
        policy: str | type[DACERFPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,  # 1e6
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.001,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        policy_delay: int = 3,
        langevin_steps: int = 20,
        langevin_step_size: float = 0.03,
        langevin_temperature: float = 0.01,
        n_sampling_steps: int = 1,
        flow_matching_coef: float = 1.0,
        compile_langevin: bool = False,
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
            env,
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
        )

        # DACER-F's own hyper-parameters (Algorithm 2)
        self.policy_delay = policy_delay
        self.langevin_steps = langevin_steps
        self.langevin_step_size = langevin_step_size
        self.langevin_temperature = langevin_temperature
        self.flow_matching_coef = flow_matching_coef
        # A copy: the caller's policy_kwargs dict stays reusable (e.g. for a SAC of the same size)
        self.policy_kwargs = {**self.policy_kwargs, "n_sampling_steps": n_sampling_steps}
        # torch.compile of the Langevin loop (an option: compiling costs ~30 s at the first update)
        self.compile_langevin = compile_langevin

        if _init_setup_model:
            self._setup_model()

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        # Switch to train mode (this affects batch norm / dropout)
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])

        critic_losses, actor_losses, flow_matching_losses, langevin_gains, lambda_fs = [], [], [], [], []

        for _ in range(gradient_steps):
            self._n_updates += 1
            # Replay: a batch (s, a_B, r, s', done), actions a_B in [-1, 1]
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            observations, actions_buffer = replay_data.observations, replay_data.actions

            # Critic update, J_Q: y = r + γ (1 - done) min_j Q̄_j(s', a'),  a' ~ π(·|s')
            critic_losses.append(self._update_critic(replay_data))

            # Actor update, every `policy_delay` critic updates
            if self._n_updates % self.policy_delay == 0:
                with frozen(self._critic_parameters()):
                    # Langevin targets a* from the replay actions (Algorithm 1), gradients w.r.t. actions only
                    langevin = compiled_langevin_targets() if self.compile_langevin else langevin_targets
                    actions_star = langevin(
                        MinQActionGradient(self.critic, observations),  # ∇_a min_j Q_j(s, a)
                        actions_buffer,
                        n_steps=self.langevin_steps,
                        step_size=self.langevin_step_size,
                        temperature=self.langevin_temperature,
                    )
                    with th.no_grad():
                        langevin_gain = self._min_q(observations, actions_star) - self._min_q(observations, actions_buffer)

                    # Policy improvement term: -Q(s, π(s)), through the one-step sampler
                    features = self.actor.extract_features(observations, self.actor.features_extractor)
                    actions_pi = self.actor.sample(features, th.randn_like(actions_star))
                    q_values_pi = self._min_q(observations, actions_pi)

                    # Flow-matching term on the path a_t = (1 - t) a_0 + t a*, target velocity a* - a_0
                    noise = th.randn_like(actions_star)
                    time = th.rand((actions_star.shape[0], 1), device=actions_star.device)
                    actions_t = (1 - time) * noise + time * actions_star
                    velocity = self.actor.velocity(features, actions_t, time)
                    flow_error = (velocity - (actions_star - noise)).pow(2).sum(dim=1, keepdim=True)

                    # λ_f ∝ ReLU(Q(s, a*) - Q(s, a_B)), per sample, mean 1 over the batch, times the Q scale
                    gain = F.relu(langevin_gain)
                    lambda_f = self.flow_matching_coef * q_values_pi.abs().mean().detach() * gain / (gain.mean() + 1e-8)

                    actor_loss = (-q_values_pi + lambda_f * flow_error).mean()
                actor_losses.append(self._checked(actor_loss, "actor loss", replay_data))
                flow_matching_losses.append(flow_error.mean().item())
                langevin_gains.append(langevin_gain.mean().item())
                lambda_fs.append(lambda_f.mean().item())

                self.actor.optimizer.zero_grad()
                actor_loss.backward()
                self.actor.optimizer.step()

            # Target networks: Q̄ <- (1 - τ) Q̄ + τ Q
            self._update_targets()

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/critic_loss", np.mean(critic_losses))
        if len(actor_losses) > 0:
            self.logger.record("train/actor_loss", np.mean(actor_losses))
            self.logger.record("train/flow_matching_loss", np.mean(flow_matching_losses))
            self.logger.record("train/langevin_gain", np.mean(langevin_gains))
            self.logger.record("train/lambda_f", np.mean(lambda_fs))
            self.logger.record("train/action_spread", self._action_spread(observations))

    @th.no_grad()
    def _action_spread(self, observations: PyTorchObs, n_states: int = 32, n_samples: int = 8) -> float:
        """
        Exploration diagnostic: standard deviation of the policy's actions over ``n_samples`` noises ``a_0``
        at fixed states, averaged over action dimensions and ``n_states`` states (0 = a deterministic policy).
        """
        features = self.actor.extract_features(observations, self.actor.features_extractor)[:n_states]
        features = features.repeat_interleave(n_samples, dim=0)
        actions = self.actor.sample(features, th.randn((features.shape[0], self.actor.action_dim), device=features.device))
        return actions.view(-1, n_samples, self.actor.action_dim).std(dim=1).mean().item()
