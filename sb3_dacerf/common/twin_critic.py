"""The base class of the package's algorithms, between SB3's ``OffPolicyAlgorithm`` and DACER-F, DACER and DSAC."""

import inspect
import math
import warnings
from abc import abstractmethod
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBufferSamples
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BaseModel, BasePolicy
from stable_baselines3.common.type_aliases import MaybeCallback
from stable_baselines3.common.utils import get_parameters_by_name, polyak_update

from sb3_dacerf.common.persistence import TwinCriticPersistence
from sb3_dacerf.common.policies import BatchRenormCritic, TwinCriticPolicy
from sb3_dacerf.common.utils import non_finite_entries
from sb3_dacerf.common.validation import (
    HyperparameterRule,
    NonFiniteLossError,
    initial_ent_coef,
    integer_at_least,
    made_env,
    resolve_target_entropy,
)

SelfTwinCriticAlgorithm = TypeVar("SelfTwinCriticAlgorithm", bound="TwinCriticAlgorithm")


@contextmanager
def frozen(parameters: Iterable[th.nn.Parameter]) -> Iterator[None]:
    """Stop gradients from reaching ``parameters`` inside the block (they still flow through them to the inputs);
    those already frozen stay frozen afterwards."""
    to_restore = [param for param in parameters if param.requires_grad]
    for param in to_restore:
        param.requires_grad_(False)
    try:
        yield
    finally:
        for param in to_restore:
            param.requires_grad_(True)


class TwinCriticAlgorithm(TwinCriticPersistence):
    """
    Base of the algorithms: an actor with actions in [-1, 1], twin critics with targets, and a temperature ``α``
    (``ent_coef``) fixed or learned towards ``target_entropy``. It holds the checks (hyper-parameters, observations,
    non-finite losses), the temperature, ``train()``'s loop over the subclass's :meth:`_update` and the target update.
    """

    #: Valid values of the numeric hyper-parameters: name -> rule. The value checked is the entry of
    #: ``policy_kwargs`` of that name if there is one (e.g. ``n_sampling_steps``), else the algorithm's attribute.
    hyperparameter_rules: ClassVar[dict[str, HyperparameterRule]] = {
        "batch_size": integer_at_least(1, "a positive integer"),
        "buffer_size": integer_at_least(1, "a positive integer (the replay buffer's capacity in transitions)"),
        "tau": HyperparameterRule(lambda value: 0 < value <= 1, "in (0, 1]"),
        "gamma": HyperparameterRule(lambda value: 0 <= value <= 1, "in [0, 1]"),
        "n_steps": integer_at_least(1, "a positive integer (1: one-step targets)"),
        "policy_delay": integer_at_least(1),
    }
    #: The initial ``α`` of ``ent_coef="auto"``, and the valid values of ``ent_coef`` in words
    auto_ent_coef: ClassVar[float] = 3.0
    ent_coef_values: ClassVar[str] = "'auto', 'auto_<initial α > 0>' (e.g. 'auto_0.5') or a number >= 0 (fixed α)"

    policy: TwinCriticPolicy
    actor: BasePolicy
    critic: BaseModel
    critic_target: BaseModel
    policy_delay: int
    ent_coef: str | float
    target_entropy: str | float
    ent_coef_optimizer: th.optim.Adam | None = None
    #: Running means ``ω̄_i`` of distributional critics' standard deviations (``None`` without them, or before the first
    #: update), logged as ``train/running_std<i>``
    running_std: list[float] | None = None

    def __init__(self, arguments: dict[str, Any]):
        """:param arguments: The algorithm's constructor's ``locals()``: those of SB3's ``OffPolicyAlgorithm`` go there
        (``env`` checked by :func:`~sb3_dacerf.common.validation.made_env`), the shared hyper-parameters become attributes"""
        names = inspect.signature(OffPolicyAlgorithm).parameters.keys() - {"env"}
        super().__init__(
            **{name: value for name, value in arguments.items() if name in names},
            env=made_env(arguments["env"], type(self).__name__, arguments["verbose"]),  # type: ignore[arg-type]  # None on load()
            supported_action_spaces=None,  # made_env() checked it, with an error that says what to do instead
            support_multi_env=True,
            sde_support=False,
        )
        self.policy_delay = arguments["policy_delay"]
        self.ent_coef = arguments["ent_coef"]
        self.target_entropy = arguments["target_entropy"]

    def _check_hyperparameters(self) -> None:
        """Check every hyper-parameter of ``hyperparameter_rules``, and ``ent_coef``: a ``ValueError`` names the first
        invalid value and its valid range."""
        for name, rule in self.hyperparameter_rules.items():
            rule.check(name, self.policy_kwargs[name] if name in self.policy_kwargs else getattr(self, name))
        initial_ent_coef(self.ent_coef, self.auto_ent_coef, self.ent_coef_values)

    def _setup_model(self) -> None:
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

    @property
    def log_alpha(self) -> th.Tensor:
        """``log α``, the temperature: a parameter of the generative actors (it scales their exploration noise)."""
        return self.actor.log_alpha  # type: ignore[return-value]

    def _setup_temperature(self, auto_target_entropy: float, learning_rate: float) -> None:
        """Set ``log α`` from ``ent_coef``, resolve ``target_entropy``, and create the temperature's optimizer (Adam,
        ``learning_rate``) when ``α`` is learned."""
        self.target_entropy = resolve_target_entropy(self.target_entropy, auto_target_entropy)
        alpha = initial_ent_coef(self.ent_coef, self.auto_ent_coef, self.ent_coef_values)
        with th.no_grad():
            self.log_alpha.fill_(math.log(alpha) if alpha > 0 else -math.inf)
        self.log_alpha.requires_grad_(isinstance(self.ent_coef, str))
        self.ent_coef_optimizer = th.optim.Adam([self.log_alpha], lr=learning_rate) if isinstance(self.ent_coef, str) else None

    def _update_temperature(self, entropy: float) -> float:
        """One step of ``log α`` on SAC's ``J(α) = log α (H - H_target)``, ``H`` the ``entropy``; returns ``J(α)`` after it."""
        assert self.ent_coef_optimizer is not None
        ent_coef_loss = self.log_alpha * (entropy - float(self.target_entropy))
        self.ent_coef_optimizer.zero_grad()
        ent_coef_loss.backward()
        self.ent_coef_optimizer.step()
        return self.log_alpha.item() * (entropy - float(self.target_entropy))

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        self.policy.set_training_mode(True)  # this affects batch norm / dropout
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        assert self.replay_buffer is not None, "train() needs the replay buffer that _setup_model() creates"
        logs: dict[str, list[float]] = {}
        for _ in range(gradient_steps):
            self._n_updates += 1
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # actions in [-1, 1]
            for key, value in self._update(replay_data).items():
                logs.setdefault(key, []).append(value)
        self.logger.record("train/n_updates", self._n_updates)
        self.logger.record("train/ent_coef", self.log_alpha.exp().item())
        for index, value in enumerate(self.running_std or [], start=1):
            self.logger.record(f"train/running_std{index}", value)
        for key, values in logs.items():
            finite = [value for value in values if math.isfinite(value)]
            if finite:
                self.logger.record(f"train/{key}", np.mean(finite))

    @abstractmethod
    def _update(self, replay_data: ReplayBufferSamples) -> dict[str, float]:
        """One gradient step on a replay batch; returns the values to log (``train()`` logs their finite means)."""

    def _critic_parameters(self) -> list[th.nn.Parameter]:
        """The critic's own parameters (not those of a features extractor shared with the actor), to freeze."""
        return self.critic.optimizer.param_groups[0]["params"]

    def _step(self, optimizer: th.optim.Optimizer, loss: th.Tensor, name: str, replay_data: ReplayBufferSamples) -> float:
        """One gradient step of ``optimizer`` on ``loss`` (checked to be finite first); returns the loss."""
        value = self._checked(loss, name, replay_data)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return value

    def _update_targets(self) -> None:
        """Polyak update of the target critics: ``Q̄ <- (1 - τ) Q̄ + τ Q`` (none with CrossQ's critics)."""
        if isinstance(self.critic, BatchRenormCritic):
            return
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
        raise NonFiniteLossError(
            f"{type(self).__name__}: non-finite {name} ({value}) at update {self._n_updates}; {cause}. No parameter was updated."
        )

    def _update_learning_rate(self, optimizers: list[th.optim.Optimizer] | th.optim.Optimizer) -> None:
        learning_rate = self.lr_schedule(self._current_progress_remaining)
        if not (isinstance(learning_rate, (int, float, np.number)) and math.isfinite(learning_rate) and learning_rate >= 0):
            raise ValueError(
                f"{type(self).__name__}: the learning-rate schedule gave {learning_rate!r} at progress remaining "
                f"{self._current_progress_remaining:.4g}; a learning rate must be a finite number >= 0 at every progress "
                "in [0, 1] (e.g. clip the schedule at 0)."
            )
        super()._update_learning_rate(optimizers)

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """See :meth:`BaseAlgorithm.predict`; an observation with NaN or infinite entries raises a ``ValueError``."""
        bad = non_finite_entries(observation)
        if bad is not None:
            raise ValueError(
                f"{type(self).__name__}.predict: the observation has non-finite entries ({bad}), from which the policy "
                "can only compute NaN actions. Replace them before calling predict (e.g. numpy.nan_to_num) or find "
                "where they come from (a sensor, a wrapper, division by zero)."
            )
        return super().predict(observation, state, episode_start, deterministic)

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        # During learn(), before any action is computed from the last observation and stepped into the environment
        bad = non_finite_entries(self._last_obs)
        if bad is not None:
            raise ValueError(
                f"{type(self).__name__}.learn: the environment returned an observation with non-finite entries ({bad}; "
                f"obs[env index, ...]) at step {self.num_timesteps}. No action was taken from it. Find the step with "
                "stable_baselines3.common.vec_env.VecCheckNan(env, raise_exception=True) and fix the environment "
                "(or clip / replace the values in a wrapper)."
            )
        return super()._sample_action(learning_starts, action_noise, n_envs)

    def learn(
        self: SelfTwinCriticAlgorithm,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str | None = None,
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfTwinCriticAlgorithm:
        """See :meth:`OffPolicyAlgorithm.learn` (TensorBoard run named after the algorithm); unlike SB3, the values logged
        since the last dump are written when it returns, and a run without any gradient step warns."""
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
            logger = self.logger
            tables: tuple[dict[str, Any], ...] = (logger.name_to_value, logger.name_to_count, logger.name_to_excluded)
            logged = [dict(table) for table in tables]
            self.dump_logs()
            for table, values in zip(tables, logged, strict=True):
                table.update(values)
        if self._n_updates == n_updates and self.num_timesteps > self._num_timesteps_at_start:
            if self.num_timesteps <= self.learning_starts:
                cause = (
                    f"learning_starts={self.learning_starts} was not reached ({self.num_timesteps} steps in all): train "
                    f"for more steps or set learning_starts below {self.num_timesteps} (RL Zoo: -params learning_starts:N)"
                )
            else:
                cause = f"check train_freq={self.train_freq} and gradient_steps={self.gradient_steps}"
            warnings.warn(
                f"{type(self).__name__}.learn() took {self.num_timesteps - self._num_timesteps_at_start} environment steps "
                f"without a single gradient step, so the policy did not learn anything: {cause}.",
                stacklevel=2,
            )
        return self

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, saved_variables = super()._get_torch_save_params()
        if self.ent_coef_optimizer is not None:
            state_dicts = [*state_dicts, "ent_coef_optimizer"]
        return state_dicts, saved_variables
