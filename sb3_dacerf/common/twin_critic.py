"""What DACER-F and DACER share: twin critics with target networks, trained by the clipped double-Q Bellman loss."""

import math
from typing import Any, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import maybe_make_env
from stable_baselines3.common.buffers import ReplayBufferSamples
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy, ContinuousCritic
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, PyTorchObs, Schedule
from stable_baselines3.common.utils import get_parameters_by_name, polyak_update
from torch.nn import functional as F

SelfTwinCriticAlgorithm = TypeVar("SelfTwinCriticAlgorithm", bound="TwinCriticAlgorithm")


class TwinCriticAlgorithm(OffPolicyAlgorithm):
    """
    Base of the generative-policy actor-critics of this package: an actor ``policy.actor`` that samples actions
    in [-1, 1] when called on observations, and twin critics ``policy.critic`` with targets ``policy.critic_target``.

    Subclasses take their own hyper-parameters (``policy_delay`` among them), pass the others on to this
    constructor, then call ``_setup_model()``, which first checks every hyper-parameter of ``HYPERPARAMETER_RULES``
    found on the algorithm or in ``policy_kwargs``. They implement ``train()`` with :meth:`_update_critic` and
    :meth:`_update_targets` around their actor update.

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, ...)
    :param env: The environment to learn from (if registered in Gym, can be str)
    :param learning_rate: learning rate for the optimizer of the actor and of the critics,
        it can be a function of the current progress remaining (from 1 to 0)
    :param kwargs: The arguments of SB3's ``OffPolicyAlgorithm``, with its defaults (those of SAC):
        ``buffer_size`` (1e6), ``learning_starts`` (100), ``batch_size`` (256), ``tau`` (0.005), ``gamma`` (0.99),
        ``train_freq`` (1), ``gradient_steps`` (1), ``action_noise`` (added to the policy's own samples during
        rollouts), ``replay_buffer_class``, ``replay_buffer_kwargs``, ``optimize_memory_usage``, ``n_steps``,
        ``policy_kwargs``, ``stats_window_size``, ``tensorboard_log``, ``verbose``, ``device``, ``seed``
    """

    policy: BasePolicy
    actor: BasePolicy
    critic: ContinuousCritic
    critic_target: ContinuousCritic

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 3e-4,
        **kwargs: Any,
    ):
        if env is not None:
            # Made here (not in the base class) so the action space is checked before SB3's own assertions
            env = maybe_make_env(env, kwargs.get("verbose", 0))
            check_action_space(env.action_space, algorithm=type(self).__name__)
        # The action space is checked above, with an error that says what to do instead
        kwargs.update(supported_action_spaces=None, support_multi_env=True, sde_support=False)
        super().__init__(policy, env, learning_rate, **kwargs)

    def _setup_model(self) -> None:
        # Before anything is built: a wrong value fails here, with its valid range
        hyperparameters = {**vars(self), **self.policy_kwargs}
        check_hyperparameters(**{name: value for name, value in hyperparameters.items() if name in HYPERPARAMETER_RULES})
        super()._setup_model()
        self._create_aliases()
        # Running mean and running var
        self.batch_norm_stats = get_parameters_by_name(self.critic, ["running_"])
        self.batch_norm_stats_target = get_parameters_by_name(self.critic_target, ["running_"])

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target

    def _min_q(self, observations: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """``min_j Q_j(s, a)`` over the critics, shape ``(batch, 1)``."""
        return th.min(th.cat(self.critic(observations, actions), dim=1), dim=1, keepdim=True).values

    def _critic_parameters(self) -> list[th.nn.Parameter]:
        """The critic's own parameters (not those of a features extractor shared with the actor), to freeze."""
        return self.critic.optimizer.param_groups[0]["params"]

    def _update_critic(self, replay_data: ReplayBufferSamples) -> float:
        """
        One gradient step on ``J_Q = E[(r + γ (1 - done) min_j Q̄_j(s', a') - Q_i(s, a))²]`` with ``a' ~ π(·|s')``.

        :return: The critic loss
        """
        # For n-step replay, discount factor is gamma**n_steps (when no early termination)
        discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
        with th.no_grad():
            next_actions = self.actor(replay_data.next_observations)
            next_q_values = th.cat(self.critic_target(replay_data.next_observations, next_actions), dim=1)
            next_q_values, _ = th.min(next_q_values, dim=1, keepdim=True)
            target_q_values = replay_data.rewards + (1 - replay_data.dones) * discounts * next_q_values

        current_q_values = self.critic(replay_data.observations, replay_data.actions)
        critic_loss = 0.5 * sum(F.mse_loss(current_q, target_q_values) for current_q in current_q_values)
        assert isinstance(critic_loss, th.Tensor)  # for type checker
        loss = self._checked(critic_loss, "critic loss", replay_data)

        self.critic.optimizer.zero_grad()
        critic_loss.backward()
        self.critic.optimizer.step()
        return loss

    def _update_targets(self) -> None:
        """Polyak update of the target critics: ``Q̄ <- (1 - τ) Q̄ + τ Q``."""
        polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
        # Copy running stats, see GH issue #996
        polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)

    def _checked(self, loss: th.Tensor, name: str, replay_data: ReplayBufferSamples) -> float:
        """Return the loss as a float; stop before the optimizer step (the model stays usable) if it is not finite."""
        value = loss.item()
        if math.isfinite(value):
            return value
        suspects = []
        for field in ("observations", "actions", "rewards", "next_observations"):
            tensors = getattr(replay_data, field)
            tensors = tensors.values() if isinstance(tensors, dict) else [tensors]
            if not all(th.isfinite(tensor).all() for tensor in tensors):
                suspects.append(field)
        cause = (
            f"the replay buffer holds non-finite {', '.join(suspects)}: the environment returned NaN/inf "
            "(wrap it with stable_baselines3.common.vec_env.VecCheckNan to find the step)"
            if suspects
            else "the Q-values diverged: lower the learning rate, scale the rewards down "
            "(e.g. VecNormalize(norm_reward=True)) or use a smaller tau"
        )
        raise RuntimeError(
            f"{type(self).__name__}: non-finite {name} ({value}) at update {self._n_updates}; {cause}. No parameter was updated."
        )

    def learn(
        self: SelfTwinCriticAlgorithm,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str | None = None,
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfTwinCriticAlgorithm:
        """See :meth:`OffPolicyAlgorithm.learn`; the TensorBoard run is named after the algorithm by default."""
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=type(self).__name__ if tb_log_name is None else tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    def _excluded_save_params(self) -> list[str]:
        return super()._excluded_save_params() + ["actor", "critic", "critic_target"]  # noqa: RUF005

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        return state_dicts, []


def check_action_space(action_space: spaces.Space, algorithm: str) -> None:
    """
    Raise a clear error unless ``action_space`` is a bounded continuous Box, the only kind a flow
    or diffusion policy can generate and rescale.

    :param action_space: The environment's action space
    :param algorithm: Name of the algorithm, for the message
    """
    if not isinstance(action_space, spaces.Box):
        raise TypeError(
            f"{algorithm} needs a continuous action space (gymnasium.spaces.Box) but the environment has {action_space}. "
            "Flow and diffusion policies generate real-valued actions: for discrete actions use DQN, PPO or QR-DQN, "
            "or give the environment a Box action space (e.g. highway-env's ContinuousAction)."
        )
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        raise ValueError(
            f"{algorithm} needs a bounded action space to rescale actions to [-1, 1], got low={action_space.low}, "
            f"high={action_space.high}. Give the Box finite bounds (e.g. gymnasium.wrappers.ClipAction after setting them)."
        )


def check_hyperparameters(**values: Any) -> None:
    """Reject hyper-parameters outside their valid range with a message naming the range."""
    for name, value in values.items():
        is_valid, valid_range = HYPERPARAMETER_RULES[name]
        if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) or not is_valid(value):
            raise ValueError(f"Invalid {name}={value!r}: it must be {valid_range}.")


def _is_count(value: Any, minimum: int) -> bool:
    return isinstance(value, (int, np.integer)) and value >= minimum


HYPERPARAMETER_RULES = {
    "batch_size": (lambda v: _is_count(v, 1), "a positive integer"),
    "tau": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "gamma": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "policy_delay": (lambda v: _is_count(v, 1), "an integer >= 1"),
    "langevin_steps": (lambda v: _is_count(v, 0), "an integer >= 0 (0 uses a_B as target)"),
    "langevin_step_size": (lambda v: v > 0, "> 0"),
    "langevin_temperature": (lambda v: v >= 0, ">= 0 (0 is noise-free gradient ascent)"),
    "n_sampling_steps": (lambda v: _is_count(v, 1), "an integer >= 1"),
    "flow_matching_coef": (lambda v: v >= 0, ">= 0"),
    "n_diffusion_steps": (lambda v: _is_count(v, 1), "an integer >= 1"),
    "alpha_learning_rate": (lambda v: v > 0, "> 0"),
    "alpha_update_interval": (lambda v: _is_count(v, 1), "an integer >= 1"),
    "entropy_samples": (lambda v: _is_count(v, 3), "an integer >= 3 (the entropy estimate fits 3 Gaussians)"),
}
