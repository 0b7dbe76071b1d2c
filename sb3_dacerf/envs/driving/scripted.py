"""
A scripted driver for the paper's driving scenarios: a baseline to compare learnt policies with, and the "competent
driver" of the reward audit (``benchmarks/driving_reward_audit.py``).

It reads only the observation (and the env's config for the scales, the action bounds and the ego's length, and with
the env's ``steering_feedforward`` the feedforward it steers on top of): pure
pursuit on the observed reference waypoints, a speed controller towards the target speed encoded in the waypoint
spacing, braking for the nearest vehicle in its corridor ahead and, with ``yield_to_crossing=True``, braking for
any vehicle whose constant-velocity prediction meets the ego's path within ``horizon`` seconds (crossing and
oncoming traffic at the intersection, vehicles in the target lane of a lane change).

Example::

    env = gym.make("DACERF-Intersection-v0")
    driver = ScriptedDriver(env)
    obs, _ = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(driver(obs))
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

from sb3_dacerf.common.buffers import DemonstrationReplayBuffer
from sb3_dacerf.envs.driving.common.abstract import PaperDrivingMixin
from sb3_dacerf.envs.driving.common.observation import EGO_FEATURES, VEHICLE_FEATURES, WAYPOINT_FEATURES


class ScriptedDriver:
    """
    Reference tracker with braking for the vehicle ahead and, optionally, yielding to crossing traffic.

    :param env: a ``DACERF-Multilane-v0`` / ``DACERF-Intersection-v0`` env (wrapped or not)
    :param yield_to_crossing: brake for vehicles predicted to meet the ego's path (see the module docstring)
    :param horizon: prediction horizon of the yielding check [s]
    :param conflict_distance: centre distance counted as a conflict [m]
    """

    def __init__(self, env: gym.Env, yield_to_crossing: bool = True, horizon: float = 2.5, conflict_distance: float = 3.0):
        unwrapped = env.unwrapped
        if not isinstance(unwrapped, PaperDrivingMixin) or not isinstance(env.action_space, spaces.Box):
            raise TypeError(
                "ScriptedDriver drives DACERF-Multilane-v0 and DACERF-Intersection-v0 (with their Box action space), "
                f"got {type(unwrapped).__name__} with action space {env.action_space}: pass one of those envs"
            )
        config = unwrapped.config
        self.position_scale, self.speed_scale = config["position_scale"], config["speed_scale"]
        self.n_waypoints = config["reference_waypoints"]
        self.waypoint_interval = config["reference_waypoint_interval"]
        self.length = unwrapped.vehicle.LENGTH
        self.yield_to_crossing = yield_to_crossing
        self.horizon, self.conflict_distance = horizon, conflict_distance
        self._unwrapped = unwrapped

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """
        :param obs: the flat observation of one env
        :return: the env's action that moves its command towards the acceleration and steering this driver wants
        """
        v_x = float(obs[0]) * self.speed_scale
        end = EGO_FEATURES + WAYPOINT_FEATURES * self.n_waypoints
        waypoints = obs[EGO_FEATURES:end].reshape(-1, WAYPOINT_FEATURES) * self.position_scale
        vehicles = obs[end:].reshape(-1, VEHICLE_FEATURES)
        vehicles = vehicles[vehicles[:, 5] > 0]

        # The waypoint spacing is the target speed times the waypoint interval.
        reference_speed = np.hypot(*(waypoints[1, :2] - waypoints[0, :2])) / self.waypoint_interval
        # Pure pursuit: look ahead ~0.8 s of travel, at least 4 m, along the waypoints.
        distances = np.hypot(waypoints[:, 0], waypoints[:, 1])
        target = waypoints[min(int(np.searchsorted(distances, max(4.0, 0.8 * v_x))), self.n_waypoints - 1), :2]
        curvature = 2 * target[1] / max(target @ target, 1e-6)
        desired_steering = np.arctan(2 * np.tan(np.arcsin(np.clip(curvature * self.length / 2, -1, 1))))
        desired_acceleration = 0.5 * (reference_speed - v_x)

        for x, y in vehicles[:, :2] * self.position_scale:
            gap = x - self.length
            if x > 0 and abs(y) < 2.5 and gap < 2.0 * max(v_x, 1.0) + 5:
                desired_acceleration = -1.0
        if self.yield_to_crossing and len(vehicles) and self._conflict(waypoints, vehicles, v_x):
            desired_acceleration = -1.0

        action_type = self._unwrapped.action_type
        feedforward = self._unwrapped._steering_feedforward() if action_type.steering_feedforward is not None else None
        return action_type.command_action(np.array([desired_acceleration, desired_steering]), feedforward).astype(np.float32)

    def _conflict(self, waypoints: np.ndarray, vehicles: np.ndarray, v_x: float) -> bool:
        """Whether a vehicle's constant-velocity prediction comes within ``conflict_distance`` of the ego's path."""
        times = np.arange(0.0, self.horizon + 1e-9, 0.25)
        # The ego moves along the waypoints at its speed, at least 2 m/s (so that a stopped ego checks it may go).
        path_s = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(waypoints[:, :2], axis=0).T))))
        ego_s = np.minimum(max(v_x, 2.0) * times, path_s[-1])
        ego = np.column_stack([np.interp(ego_s, path_s, waypoints[:, 0]), np.interp(ego_s, path_s, waypoints[:, 1])])
        for x, y, cos_phi, sin_phi, speed, _ in vehicles:
            position = np.array([x, y]) * self.position_scale
            if position[0] < 0 and cos_phi > 0.9:
                continue  # following the ego in its direction: not ours to yield to
            velocity = speed * self.speed_scale * np.array([cos_phi, sin_phi])
            other = position + times[:, None] * velocity
            if np.min(np.hypot(*(other - ego).T)) < self.conflict_distance:
                return True
        return False


def add_scripted_transitions(model: OffPolicyAlgorithm, n_transitions: int, **driver_kwargs: Any) -> None:
    """
    Put ``n_transitions`` of the scripted driver in an off-policy model's replay buffer (demonstrations), before it
    learns: each env of the model's own training ``VecEnv`` is driven by a :class:`ScriptedDriver`, and the
    transitions are stored as SB3 stores its own rollouts (raw observations and rewards with ``VecNormalize``, whose
    statistics see them too; actions in the policy's ``[-1, 1]`` scale; time limits marked as such). They do not count
    as the model's steps (``model.num_timesteps`` stays as it is), and they stay in the buffer until it wraps around.
    With a :class:`~sb3_dacerf.common.buffers.DemonstrationReplayBuffer` they go to its demonstrations' part, which
    keeps them and gives them a fixed share of every batch.

    With DACERF they are imitated as well as evaluated: its actor's flow-matching term fits the replay actions
    (moved by the Langevin steps), so the first updates already copy the driver.

    Example::

        model = DACERF("MlpPolicy", VecNormalize(DummyVecEnv([lambda: gym.make("DACERF-Intersection-v0")])))
        add_scripted_transitions(model, 10_000)
        model.learn(100_000)

    :param model: an SB3 off-policy model (DACERF, DACER, SAC, TD3, ...) on a driving scenario's ``DummyVecEnv``
        (possibly inside ``VecNormalize``): the drivers read the env objects, so they must live in this process
    :param n_transitions: how many transitions to add (rounded up to a multiple of the number of envs)
    :param driver_kwargs: arguments of :class:`ScriptedDriver` (``yield_to_crossing``, ...)
    :raises ValueError: a negative ``n_transitions``, a model whose envs are not in a ``DummyVecEnv``, or more
        transitions than a ``DemonstrationReplayBuffer``'s demonstrations' part has room for
    :raises TypeError: envs that are not driving scenarios (from :class:`ScriptedDriver`)
    """
    from stable_baselines3.common.vec_env import DummyVecEnv

    if n_transitions < 0:
        raise ValueError(f"n_transitions must be >= 0, got {n_transitions}")
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
    drivers = [ScriptedDriver(single, **driver_kwargs) for single in inner.envs]
    model._last_obs = env.reset()  # type: ignore[assignment]  # a VecEnv's observations are arrays
    model._last_original_obs = vec_normalize.get_original_obs() if vec_normalize is not None else model._last_obs
    with recording:
        for _ in range(n_steps):
            raw = model._last_original_obs
            actions = np.stack([driver(obs) for driver, obs in zip(drivers, raw, strict=True)])  # type: ignore[arg-type]
            new_obs, rewards, dones, infos = env.step(actions)
            model._store_transition(buffer, model.policy.scale_action(actions), new_obs, rewards, dones, infos)  # type: ignore[arg-type]
