"""
DACER-F whose Langevin chains persist across updates: a measurement (``learning_curves.py --variants
dacerf-chain``), not an option of the package.

Every replay transition keeps the state of its own Langevin chain beside the replay buffer. The chain starts at the
replay action ``a_B``; each time the transition is in an actor update's batch, Algorithm 1's ``N_l`` steps go on from
where its last update left it, and the flow is trained towards that chain's new state ``a*``. ``λ_f`` stays the
paper's ``ReLU(Q(s, a*) - Q(s, a_B))`` against the replay action. DIPO, whose action-gradient targets DACER-F's
Langevin targets extend, keeps its improved actions in the same way. The critics learn from the replay actions.
"""

from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer, ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize

from sb3_dacerf import DACERF
from sb3_dacerf.dacerf.policies import MinQActionGradient


class ChainReplayBuffer(ReplayBuffer):
    """SB3's ``ReplayBuffer`` that also keeps each transition's Langevin chain state (:attr:`chain_actions`, the
    stored action until a chain moves it) and the indices of the last batch it sampled."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        if self.optimize_memory_usage:
            raise ValueError("ChainReplayBuffer does not take optimize_memory_usage=True: set it to False.")
        self.chain_actions = np.zeros_like(self.actions)
        self.sampled: tuple[np.ndarray, np.ndarray] | None = None

    def add(self, obs: Any, next_obs: Any, action: Any, reward: Any, done: Any, infos: Any) -> None:
        position = self.pos
        super().add(obs, next_obs, action, reward, done, infos)
        self.chain_actions[position] = self.actions[position]

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> ReplayBufferSamples:
        # SB3's ReplayBuffer._get_samples (same random draws), keeping the indices
        env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))
        self.sampled = (batch_inds, env_indices)
        data = (
            self._normalize_obs(self.observations[batch_inds, env_indices, :], env),
            self.actions[batch_inds, env_indices, :],
            self._normalize_obs(self.next_observations[batch_inds, env_indices, :], env),
            (self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices])).reshape(-1, 1),
            self._normalize_reward(self.rewards[batch_inds, env_indices].reshape(-1, 1), env),
        )
        return ReplayBufferSamples(*tuple(map(self.to_torch, data)))

    def sampled_chains(self) -> th.Tensor:
        """The chain states of the last sampled batch."""
        assert self.sampled is not None, "sample() first"
        batch_inds, env_indices = self.sampled
        return self.to_torch(self.chain_actions[batch_inds, env_indices])

    def store_sampled_chains(self, actions: th.Tensor) -> None:
        """Write the new chain states of the last sampled batch."""
        assert self.sampled is not None, "sample() first"
        batch_inds, env_indices = self.sampled
        self.chain_actions[batch_inds, env_indices] = actions.detach().cpu().numpy()


class PersistentLangevinDACERF(DACERF):
    """:class:`~sb3_dacerf.DACERF` whose actor updates continue each replay transition's Langevin chain
    (:class:`ChainReplayBuffer`, the default replay buffer here)."""

    replay_buffer: ChainReplayBuffer

    def __init__(self, policy: Any, env: Any, **kwargs: Any):
        if kwargs.get("replay_buffer_class") not in (None, ChainReplayBuffer):
            raise ValueError("PersistentLangevinDACERF keeps its chains in a ChainReplayBuffer: leave replay_buffer_class unset.")
        if kwargs.get("n_steps", 1) != 1:
            raise ValueError("PersistentLangevinDACERF takes n_steps=1 (its buffer is SB3's one-step ReplayBuffer).")
        kwargs["replay_buffer_class"] = ChainReplayBuffer
        super().__init__(policy, env, **kwargs)
        self._in_actor_update = False

    @classmethod
    def load(cls, path: Any, *args: Any, custom_objects: dict[str, Any] | None = None, **kwargs: Any) -> Any:
        """:meth:`DACERF.load`, with this class's replay buffer class (a saved model names it as a pickle)."""
        custom_objects = {"replay_buffer_class": ChainReplayBuffer, **(custom_objects or {})}
        return super().load(path, *args, custom_objects=custom_objects, **kwargs)

    def actor_loss_terms(self, replay_data: Any) -> dict[str, th.Tensor]:
        self._in_actor_update = True
        try:
            return super().actor_loss_terms(replay_data)
        finally:
            self._in_actor_update = False

    def _langevin(self, gradient: MinQActionGradient, actions: th.Tensor) -> th.Tensor:
        if not self._in_actor_update:  # langevin_targets() on any actions: Algorithm 1 from them
            return super()._langevin(gradient, actions)
        q_values_buffer = gradient.min_q(actions)
        targets = super()._langevin(gradient, self.replay_buffer.sampled_chains())
        gradient.start_min_q = q_values_buffer  # λ_f against Q(s, a_B), the paper's
        self.replay_buffer.store_sampled_chains(targets)
        return targets
