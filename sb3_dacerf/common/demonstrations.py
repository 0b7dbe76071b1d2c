"""
Demonstrations in an off-policy model's replay buffer: :func:`add_scripted_transitions` drives the model's own
training envs with a scripted driver (by default the driving scenarios'
:class:`~sb3_dacerf.envs.driving.scripted.ScriptedDriver`) and stores the transitions as SB3 stores its rollouts.

The environments know nothing of models and buffers: this module is where the two meet. The drivers are imported
when the function runs, so importing this module does not import highway-env.

Example::

    model = DACERF(
        "MlpPolicy",
        VecNormalize(DummyVecEnv([lambda: gym.make("DACERF-Intersection-v0")])),
        replay_buffer_class=DemonstrationReplayBuffer,
        replay_buffer_kwargs=dict(demonstration_fraction=0.5),
    )
    add_scripted_transitions(model, 10_000)
    model.learn(100_000)
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_dacerf.common.buffers import DemonstrationReplayBuffer

__all__ = ["add_scripted_transitions"]


def add_scripted_transitions(
    model: OffPolicyAlgorithm,
    n_transitions: int,
    driver: Callable[..., Callable[[np.ndarray], np.ndarray]] | None = None,
    **driver_kwargs: Any,
) -> None:
    """
    Put ``n_transitions`` of a scripted driver in an off-policy model's replay buffer (demonstrations), before it
    learns: each env of the model's own training ``VecEnv`` is driven by ``driver(env, **driver_kwargs)``, and the
    transitions are stored as SB3 stores its own rollouts (raw observations and rewards with ``VecNormalize``, whose
    statistics see them too; actions in the policy's ``[-1, 1]`` scale; time limits marked as such). They do not count
    as the model's steps (``model.num_timesteps`` stays as it is), and they stay in the buffer until it wraps around.
    With a :class:`~sb3_dacerf.common.buffers.DemonstrationReplayBuffer` they go to its demonstrations' part, which
    keeps them and gives them a fixed share of every batch.

    With DACERF they are imitated as well as evaluated: its actor's flow-matching term fits the replay actions
    (moved by the Langevin steps), so the first updates already copy the driver.

    :param model: an SB3 off-policy model (DACERF, DACER, SAC, TD3, ...) on a driving scenario's ``DummyVecEnv``
        (possibly inside ``VecNormalize``): the drivers read the env objects, so they must live in this process
    :param n_transitions: how many transitions to add (rounded up to a multiple of the number of envs)
    :param driver: the demonstrator: a class (or function) that takes one env and returns a function from its raw
        observation to its action; by default :class:`~sb3_dacerf.envs.driving.scripted.ScriptedDriver`, at the
        intersection also :class:`~sb3_dacerf.envs.driving.scripted.JunctionDriver`
    :param driver_kwargs: arguments of the driver (``yield_to_crossing``, ...)
    :raises ValueError: a negative ``n_transitions``, a model whose envs are not in a ``DummyVecEnv``, or more
        transitions than a ``DemonstrationReplayBuffer``'s demonstrations' part has room for
    :raises TypeError: envs that the driver does not drive (from its constructor)
    """
    if n_transitions < 0:
        raise ValueError(f"n_transitions must be >= 0, got {n_transitions}")
    if driver is None:
        from sb3_dacerf.envs.driving.scripted import ScriptedDriver

        driver = ScriptedDriver
    env = model.get_env()
    vec_normalize = model.get_vec_normalize_env()
    inner = vec_normalize.venv if vec_normalize is not None else env
    if env is None or not isinstance(inner, DummyVecEnv):
        raise ValueError(
            f"add_scripted_transitions needs the model's envs in this process (a DummyVecEnv, possibly in VecNormalize), "
            f"got {type(inner).__name__}: fill the buffer of a model on a DummyVecEnv (SubprocVecEnv keeps its envs in "
            "other processes)"
        )
    n_steps = -(-n_transitions // env.num_envs)
    buffer = model.replay_buffer
    recording: AbstractContextManager[None] = nullcontext()
    if isinstance(buffer, DemonstrationReplayBuffer):
        free = buffer.demonstration_capacity - buffer.n_demonstrations()
        if n_steps * env.num_envs > free:
            raise ValueError(
                f"{n_steps * env.num_envs} demonstrations do not fit in the {free} free places of the buffer's "
                "demonstrations: pass a larger demonstration_size in replay_buffer_kwargs (or add fewer)"
            )
        recording = buffer.recording_demonstrations()
    envs: list[gym.Env] = inner.envs
    drivers = [driver(single, **driver_kwargs) for single in envs]
    model._last_obs = env.reset()  # type: ignore[assignment]  # a VecEnv's observations are arrays
    model._last_original_obs = vec_normalize.get_original_obs() if vec_normalize is not None else model._last_obs
    with recording:
        for _ in range(n_steps):
            raw = model._last_original_obs
            actions = np.stack([act(obs) for act, obs in zip(drivers, raw, strict=True)])  # type: ignore[arg-type]
            new_obs, rewards, dones, infos = env.step(actions)
            model._store_transition(buffer, model.policy.scale_action(actions), new_obs, rewards, dones, infos)  # type: ignore[arg-type]
