"""
What DACER-F and DACER share: twin critics with target networks, trained by the clipped double-Q Bellman loss.

The algorithm is here; its checks are in :mod:`sb3_dacerf.common.validation` and its saving and loading in
:mod:`sb3_dacerf.common.persistence`, whose public names this module re-exports.
"""

import warnings
from collections.abc import Callable
from typing import Any, TypeVar

import torch as th
from stable_baselines3.common.base_class import maybe_make_env
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBufferSamples
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, PyTorchObs, Schedule
from stable_baselines3.common.utils import get_parameters_by_name, polyak_update

from sb3_dacerf.common.ensemble import BatchRenormCritic, EnsembleCritic
from sb3_dacerf.common.persistence import TwinCriticPersistence, saved_algorithm_name
from sb3_dacerf.common.policies import GenerativeActor, TwinCriticPolicy
from sb3_dacerf.common.validation import (
    HyperparameterRule,
    NonFiniteLossError,
    TwinCriticChecks,
    UnsupportedActionSpaceError,
    check_action_space,
    integer_at_least,
    resolve_target_entropy,
)

__all__ = [
    "HyperparameterRule",
    "NonFiniteLossError",
    "TwinCriticAlgorithm",
    "UnsupportedActionSpaceError",
    "check_action_space",
    "integer_at_least",
    "min_q",
    "resolve_target_entropy",
    "saved_algorithm_name",
]

SelfTwinCriticAlgorithm = TypeVar("SelfTwinCriticAlgorithm", bound="TwinCriticAlgorithm")


class TwinCriticAlgorithm(TwinCriticChecks, TwinCriticPersistence):
    """
    Base of the generative-policy actor-critics of this package: an actor ``policy.actor`` that samples actions
    in [-1, 1] when called on observations, and twin critics ``policy.critic`` with targets ``policy.critic_target``.

    Subclasses take their own hyper-parameters (``policy_delay`` among them), pass the others on to this
    constructor, then call ``_setup_model()``, which first calls :meth:`_check_hyperparameters`: each rule of the
    class attribute ``hyperparameter_rules`` is checked against the hyper-parameter of its name. A subclass adds the
    rules of its own hyper-parameters to it (``{**TwinCriticAlgorithm.hyperparameter_rules, ...}``) and overrides
    :meth:`_check_hyperparameters` for checks a range cannot express. Subclasses implement ``train()`` with
    :meth:`_update_critic` and :meth:`_update_targets` around their actor update. The checks (hyper-parameter rules,
    non-finite losses and observations) come from :class:`~sb3_dacerf.common.validation.TwinCriticChecks`, saving and
    loading from :class:`~sb3_dacerf.common.persistence.TwinCriticPersistence`.

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

    policy: TwinCriticPolicy
    actor: GenerativeActor
    critic: EnsembleCritic
    critic_target: EnsembleCritic

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
        # SB3 annotates OffPolicyAlgorithm's env without None, which its own load() passes
        super().__init__(policy, env, learning_rate, **kwargs)  # type: ignore[arg-type]

    def _setup_model(self) -> None:
        # Before anything is built: a wrong value fails here, with its valid range
        self._check_hyperparameters()
        with warnings.catch_warnings():
            if self.replay_buffer_class is NStepReplayBuffer and self.replay_buffer_kwargs.get("n_steps") == self.n_steps:
                # A loaded model's NStepReplayBuffer is the one SB3 chose for its n_steps, not a custom buffer whose
                # n_steps SB3 would ignore: its warning would be wrong here
                warnings.filterwarnings("ignore", message=r"`n_steps=\d+` is ignored because a custom")
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
        return min_q(self.critic, observations, actions)

    def _critic_parameters(self) -> list[th.nn.Parameter]:
        """The critic's own parameters (not those of a features extractor shared with the actor), to freeze."""
        return self.critic.optimizer.param_groups[0]["params"]

    def _update_critic(self, replay_data: ReplayBufferSamples) -> float:
        """
        One gradient step on ``J_Q = E[(r + γ (1 - done) min_j Q̄_j(s', a') - Q_i(s, a))²]`` with ``a' ~ π(·|s')``.

        :return: The critic loss
        """
        critic_loss = self.critic_terms(replay_data)["loss"]
        loss = self._checked(critic_loss, "critic loss", replay_data)

        self.critic.optimizer.zero_grad()
        critic_loss.backward()
        self.critic.optimizer.step()
        return loss

    def critic_terms(self, replay_data: ReplayBufferSamples) -> dict[str, th.Tensor]:
        """
        The critic loss ``J_Q = 0.5 Σ_i mean((y - Q_i(s, a))²)`` on a replay batch, with the Bellman target
        ``y = r + γ (1 - done) min_j Q̄_j(s', a')``, ``a' ~ π(·|s')`` (the critics themselves instead of the targets
        with CrossQ's critics, whose running statistics this pass updates).

        :param replay_data: A batch of the replay buffer
        :return: ``loss`` (differentiable with respect to the critics), ``target_q_values`` ``y`` ``(batch, 1)`` and
            ``current_q_values`` ``(n_critics, batch, 1)`` (detached)
        """
        # For n-step replay, discount factor is gamma**n_steps (when no early termination)
        discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
        with th.no_grad():
            next_actions = self.actor(replay_data.next_observations)
        critic = self.critic
        if isinstance(critic, BatchRenormCritic):
            # CrossQ's critics (critic="batch_renorm"): no target networks; one forward pass over (s, a) and (s', a') so
            # that the batch statistics are those of both, in training mode for this pass only
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
                next_q_values = self.critic_target.q_values(replay_data.next_observations, next_actions)
            current_q_values = critic.q_values(replay_data.observations, replay_data.actions)
        with th.no_grad():
            # (n_critics, batch, 1) -> (batch, 1)
            target_q_values = replay_data.rewards + (1 - replay_data.dones) * discounts * next_q_values.min(dim=0).values

        # 0.5 * sum_j mean((Q_j - y)^2): every critic's MSE, from the stacked Q-values in one pass
        critic_loss = 0.5 * (current_q_values - target_q_values).pow(2).mean(dim=(1, 2)).sum()
        return dict(loss=critic_loss, target_q_values=target_q_values, current_q_values=current_q_values.detach())

    def _update_targets(self) -> None:
        """Polyak update of the target critics: ``Q̄ <- (1 - τ) Q̄ + τ Q`` (none with CrossQ's critics)."""
        if isinstance(self.critic, BatchRenormCritic):  # CrossQ's critics have no target networks
            return
        polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
        # Copy running stats, see GH issue #996
        polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)

    def learn(
        self: SelfTwinCriticAlgorithm,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str | None = None,
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfTwinCriticAlgorithm:
        """
        See :meth:`OffPolicyAlgorithm.learn`; the TensorBoard run is named after the algorithm by default.

        Unlike SB3, the values logged since the last ``log_interval`` dump are written when ``learn()`` returns (a run
        shorter than ``log_interval`` episodes still has its ``train/*`` scalars), and a run that ended without any
        gradient step (``learning_starts`` not reached) warns.
        """
        n_updates = self._n_updates
        super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=type(self).__name__ if tb_log_name is None else tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )
        if self.logger.name_to_value:
            # Written, then kept readable in logger.name_to_value as after SB3's learn() (dump() would clear them)
            tables: tuple[dict[str, Any], ...] = (
                self.logger.name_to_value,
                self.logger.name_to_count,
                self.logger.name_to_excluded,
            )
            logged = [dict(table) for table in tables]
            self.dump_logs()
            for table, values in zip(tables, logged, strict=True):
                table.update(values)
        if self._n_updates == n_updates and self.num_timesteps > self._num_timesteps_at_start:
            name = type(self).__name__
            if self.num_timesteps <= self.learning_starts:
                cause = (
                    f"learning_starts={self.learning_starts} was not reached ({self.num_timesteps} steps in all): train "
                    f"for more steps or set learning_starts below {self.num_timesteps} (RL Zoo: -params learning_starts:N)"
                )
            else:
                cause = f"check train_freq={self.train_freq} and gradient_steps={self.gradient_steps}"
            warnings.warn(
                f"{name}.learn() took {self.num_timesteps - self._num_timesteps_at_start} environment steps without a "
                f"single gradient step, so the policy did not learn anything: {cause}.",
                stacklevel=2,
            )
        return self


def min_q(critic: Callable[[PyTorchObs, th.Tensor], Any], observations: PyTorchObs, actions: th.Tensor) -> th.Tensor:
    """
    ``min_j Q_j(s, a)`` over the critics of an :class:`~sb3_dacerf.common.ensemble.EnsembleCritic` (DACERF's,
    DACER's) or of an SB3 ``ContinuousCritic`` (SAC's, TD3's), shape ``(batch, 1)``.
    """
    if isinstance(critic, EnsembleCritic):
        return critic.q_values(observations, actions).min(dim=0).values
    return th.min(th.cat(critic(observations, actions), dim=1), dim=1, keepdim=True).values


def _cat_observations(first: PyTorchObs, second: PyTorchObs) -> PyTorchObs:
    """Two batches of observations (tensors, or dicts of tensors) as one."""
    if isinstance(first, dict):
        assert isinstance(second, dict)
        return {key: th.cat([first[key], second[key]], dim=0) for key in first}
    assert isinstance(first, th.Tensor) and isinstance(second, th.Tensor)
    return th.cat([first, second], dim=0)
