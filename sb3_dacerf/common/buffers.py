"""
A replay buffer that keeps demonstrations apart from the agent's own transitions and draws a fixed share of every
batch from them, as RLPD ("Efficient Online Reinforcement Learning with Offline Data", Ball et al., 2023) samples
its offline data. In a plain buffer, demonstrations put there before learning make up a share of each batch that
falls as the agent's own transitions fill it (10,000 of them are a tenth of the batch after 90,000 steps); here the
share stays what it was set to.

Example::

    model = DACERF(
        "MlpPolicy",
        env,
        replay_buffer_class=DemonstrationReplayBuffer,
        replay_buffer_kwargs=dict(demonstration_fraction=0.5),
    )
    add_scripted_transitions(model, 10_000)  # sb3_dacerf.common.demonstrations: goes to the demonstrations
    model.learn(100_000)

Any other code adds demonstrations inside ``with model.replay_buffer.recording_demonstrations():``.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize


class DemonstrationSamples(ReplayBufferSamples):
    """
    A batch of :class:`DemonstrationReplayBuffer`: its first ``n_demonstrations`` transitions are demonstrations,
    whose flow-matching targets DACERF takes from :meth:`imitation_targets`.
    """

    n_demonstrations: int = 0
    #: The buffer's ``demonstration_targets``
    demonstration_targets: str = "langevin"

    def imitation_targets(self, targets: th.Tensor, weights: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """
        The flow-matching targets DACERF fits on this batch, and their weights (see
        :meth:`sb3_dacerf.dacerf.dacerf.DACERF.imitation_targets`).

        :param targets: The Langevin targets ``a*`` of every transition ``(batch, action_dim)``
        :param weights: Their weights ``λ_f`` ``(batch, 1)``
        :return: ``targets`` and ``weights`` themselves with ``demonstration_targets="langevin"``; with ``"actions"``,
            the leading demonstrations' own actions in place of their ``a*``, each at the batch's mean weight
        """
        n_demonstrations = self.n_demonstrations
        if self.demonstration_targets == "langevin" or n_demonstrations == 0:
            return targets, weights
        targets = th.cat((self.actions[:n_demonstrations], targets[n_demonstrations:]))
        weights = th.cat((weights.mean().expand(n_demonstrations, 1), weights[n_demonstrations:]))
        return targets, weights


class DemonstrationReplayBuffer(ReplayBuffer):
    """
    SB3's :class:`~stable_baselines3.common.buffers.ReplayBuffer` for the agent's transitions, plus a second one of
    ``demonstration_size`` transitions for demonstrations, which the agent's transitions never overwrite. Once both
    hold data, ``round(demonstration_fraction * batch_size)`` transitions of each batch come from the demonstrations
    and the rest from the agent's own; while one of them is empty, the whole batch comes from the other.
    ``size()``, ``full`` and ``pos`` describe the agent's part, as in a plain buffer.

    :param buffer_size: capacity of the agent's part (the ``buffer_size`` of the algorithm)
    :param observation_space: observation space
    :param action_space: action space
    :param device: PyTorch device
    :param n_envs: number of parallel environments
    :param optimize_memory_usage: as in :class:`~stable_baselines3.common.buffers.ReplayBuffer` (agent's part only)
    :param handle_timeout_termination: as in :class:`~stable_baselines3.common.buffers.ReplayBuffer`
    :param demonstration_fraction: share of each batch drawn from the demonstrations, in ``[0, 1]``
    :param demonstration_size: capacity of the demonstrations' part, in transitions
    :param demonstration_targets: what DACERF's flow-matching (imitation) term fits for the demonstrations of a batch:
        ``"langevin"`` treats them as any replay action (Langevin targets, weighted by their gain); ``"actions"`` fits
        the demonstrated actions themselves, each with the batch's mean weight ``λ_f`` (other algorithms ignore it)
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        demonstration_fraction: float = 0.5,
        demonstration_size: int = 100_000,
        demonstration_targets: str = "langevin",
    ):
        if demonstration_targets not in ("langevin", "actions"):
            raise ValueError(f"Invalid demonstration_targets={demonstration_targets!r}: it must be 'langevin' or 'actions'.")
        if not 0.0 <= demonstration_fraction <= 1.0:
            raise ValueError(
                f"demonstration_fraction is the share of each batch drawn from the demonstrations and must be in "
                f"[0, 1], got {demonstration_fraction}"
            )
        if demonstration_size < n_envs:
            raise ValueError(f"demonstration_size must hold at least one step of the {n_envs} env(s), got {demonstration_size}")
        super().__init__(
            buffer_size,
            observation_space,
            action_space,
            device=device,
            n_envs=n_envs,
            optimize_memory_usage=optimize_memory_usage,
            handle_timeout_termination=handle_timeout_termination,
        )
        self.demonstration_fraction = float(demonstration_fraction)
        self.demonstration_targets = demonstration_targets
        self.demonstrations = ReplayBuffer(
            demonstration_size,
            observation_space,
            action_space,
            device=device,
            n_envs=n_envs,
            handle_timeout_termination=handle_timeout_termination,
        )
        self._recording = False

    @contextmanager
    def recording_demonstrations(self) -> Iterator[None]:
        """Within this context, :meth:`add` stores into the demonstrations' part."""
        self._recording = True
        try:
            yield
        finally:
            self._recording = False

    @property
    def demonstration_capacity(self) -> int:
        """How many transitions the demonstrations' part holds before it overwrites its oldest."""
        return self.demonstrations.buffer_size * self.n_envs

    def n_demonstrations(self) -> int:
        """Transitions in the demonstrations' part."""
        return self.demonstrations.size() * self.n_envs

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """Store one step of transitions: in the demonstrations' part within :meth:`recording_demonstrations`."""
        if self._recording:
            self.demonstrations.add(obs, next_obs, action, reward, done, infos)
        else:
            super().add(obs, next_obs, action, reward, done, infos)

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> DemonstrationSamples:
        """
        :param batch_size: transitions in the batch
        :param env: the ``VecNormalize`` wrapper whose statistics normalise the observations and rewards, if any
        :return: ``round(demonstration_fraction * batch_size)`` demonstrations first, then the agent's transitions
            (their number in the batch's ``n_demonstrations``)
        """
        self.demonstrations.device = self.device  # the model's load() moves the buffer to its device
        n_demonstrations = round(self.demonstration_fraction * batch_size)
        if self.demonstrations.size() == 0:
            n_demonstrations = 0
        elif self.size() == 0:
            n_demonstrations = batch_size
        parts = []
        if n_demonstrations > 0:
            parts.append(self.demonstrations.sample(n_demonstrations, env=env))
        if n_demonstrations < batch_size:
            parts.append(super().sample(batch_size - n_demonstrations, env=env))
        fields = [None if values[0] is None else th.cat(values) for values in zip(*parts, strict=True)]
        samples = DemonstrationSamples(*fields)  # type: ignore[arg-type]  # only the optional discounts can be None
        samples.n_demonstrations = n_demonstrations
        samples.demonstration_targets = self.demonstration_targets
        return samples
