"""
Faults and bad input, as a user meets them: a save that fails half-way, NaN observations, conflicting or infinite
hyper-parameters, another algorithm's file, unsupported action spaces, runs too short to learn or to log.
"""

import os
import pickle
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common import save_util
from stable_baselines3.common.envs import SimpleMultiObsEnv

from sb3_dacerf import DACER, DACERF

# The tests take the model_class and fast fixtures of conftest.py: both algorithms, or the one parametrised
ONLY_DACERF = pytest.mark.parametrize("model_class", [DACERF], ids=["DACERF"])


def fail_after_writing(monkeypatch, module, name: str) -> None:
    """Make ``module.name(obj, file)`` write part of its output, then fail as on a full disk."""

    def write_then_fail(obj, file, *args, **kwargs):
        file.write(b"\0" * 4096)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(module, name, write_then_fail)


def test_failed_save_leaves_the_previous_model_intact(tmp_path, monkeypatch, model_class, fast):
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    model.save(tmp_path / "model")
    os.chmod(tmp_path / "model.zip", 0o640)
    observations = np.stack([model.observation_space.sample() for _ in range(8)])
    expected, _ = model.predict(observations, deterministic=True)

    model.learn(60)  # a changed model, whose save fails half-way
    with monkeypatch.context() as patch:
        fail_after_writing(patch, th, "save")
        with pytest.raises(OSError, match="No space left"):
            model.save(tmp_path / "model")
    assert os.listdir(tmp_path) == ["model.zip"]  # no temporary file left behind
    loaded = type(model).load(tmp_path / "model")
    np.testing.assert_array_equal(loaded.predict(observations, deterministic=True)[0], expected)

    model.save(tmp_path / "model")  # a save that succeeds replaces the file and keeps its permissions
    assert type(model).load(tmp_path / "model.zip").num_timesteps == 60
    assert os.stat(tmp_path / "model.zip").st_mode & 0o777 == 0o640


@ONLY_DACERF
def test_failed_replay_buffer_save_leaves_the_previous_buffer_intact(tmp_path, monkeypatch, model_class, fast):
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, **{**fast, "learning_starts": 10})
    model.learn(30)
    model.save_replay_buffer(tmp_path / "buffer")
    model.learn(30, reset_num_timesteps=False)
    with monkeypatch.context() as patch:
        fail_after_writing(patch, save_util.pickle, "dump")
        with pytest.raises(OSError, match="No space left"):
            model.save_replay_buffer(tmp_path / "buffer")
    assert os.listdir(tmp_path) == ["buffer.pkl"]
    model.load_replay_buffer(tmp_path / "buffer.pkl")
    assert model.replay_buffer.size() == 30


def test_predict_refuses_non_finite_observations(model_class, fast):
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    with pytest.raises(ValueError, match=r"non-finite entries \(obs\[0\] = nan, obs\[2\] = inf\)"):
        model.predict(np.array([np.nan, 0.0, np.inf], dtype=np.float32))
    with pytest.raises(ValueError, match=r"obs\[1, 1\] = -inf"):
        model.predict(np.array([[0.0, 0.0, 0.0], [0.0, -np.inf, 0.0]], dtype=np.float32))


def test_predict_names_the_dict_key_of_a_non_finite_entry(model_class, fast):
    model = model_class("MultiInputPolicy", SimpleMultiObsEnv(discrete_actions=False), **fast)
    observation = model.observation_space.sample()
    observation["vec"][3] = np.nan
    with pytest.raises(ValueError, match=r"obs\['vec'\]\[3\] = nan"):
        model.predict(observation)


class NanObservationAt(gym.Wrapper):
    """Pendulum whose observation at one step is NaN; records the actions it receives."""

    def __init__(self, step: int):
        super().__init__(gym.make("Pendulum-v1"))
        self.nan_step, self.steps, self.actions = step, 0, []

    def step(self, action):
        self.actions.append(np.array(action))
        self.steps += 1
        observation, reward, terminated, truncated, info = self.env.step(action)
        if self.steps == self.nan_step:
            observation = np.array([0.0, np.nan, 0.0], dtype=np.float32)
        return observation, reward, terminated, truncated, info


@pytest.mark.parametrize("nan_step", [20, 70])  # during the random warm-up and when the policy acts
def test_learn_stops_at_a_non_finite_observation_before_acting_on_it(nan_step, model_class, fast):
    env = NanObservationAt(nan_step)
    # No gradient step between the NaN observation and the next action: a batch holding that transition would stop
    # training first, with the non-finite critic loss error (tested in test_dacerf.py)
    model = model_class("MlpPolicy", env, seed=0, train_freq=(1_000, "step"), **fast)
    message = rf"environment returned an observation with non-finite entries \(obs\[0, 1\] = nan.*step {nan_step}.*VecCheckNan"
    with pytest.raises(ValueError, match=message):
        model.learn(100)
    assert len(env.actions) == nan_step  # no action followed the NaN observation
    assert all(np.isfinite(action).all() for action in env.actions)


def test_sampling_steps_are_policy_arguments():
    assert DACERF("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(n_sampling_steps=8)).actor.n_sampling_steps == 8
    assert DACERF("MlpPolicy", "Pendulum-v1").policy_kwargs["n_sampling_steps"] == 1
    assert DACER("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(n_diffusion_steps=5)).actor.n_diffusion_steps == 5
    assert DACER("MlpPolicy", "Pendulum-v1").actor.n_diffusion_steps == 20
    with pytest.raises(TypeError, match="unexpected keyword argument 'n_sampling_steps'"):
        DACERF("MlpPolicy", "Pendulum-v1", n_sampling_steps=4)


class NanRewards(gym.Wrapper):
    """Pendulum whose rewards are all NaN."""

    def step(self, action):
        observation, _, terminated, truncated, info = self.env.step(action)
        return observation, float("nan"), terminated, truncated, info


@pytest.mark.parametrize("expected", [ValueError, RuntimeError])
def test_non_finite_loss_is_caught_as_value_error_and_as_runtime_error(expected, model_class, fast):
    # RL Zoo's objective prunes a trial on (AssertionError, ValueError); code written for `except RuntimeError` still works
    model = model_class("MlpPolicy", NanRewards(gym.make("Pendulum-v1")), seed=0, **fast)
    with pytest.raises(expected, match=r"non-finite critic loss .*non-finite rewards"):
        model.learn(100)


def test_unsupported_action_space_is_an_assertion_error_like_sb3(model_class, fast):
    for expected in (AssertionError, TypeError):
        with pytest.raises(expected, match=r"needs a continuous action space.*Discrete\(2\).*DQN"):
            model_class("MlpPolicy", "CartPole-v1", **fast)


def test_load_names_the_algorithm_a_file_holds(tmp_path):
    SAC("MlpPolicy", "Pendulum-v1", buffer_size=1, policy_kwargs=dict(net_arch=[8])).save(tmp_path / "sac")
    DACERF("MlpPolicy", "Pendulum-v1", buffer_size=1, policy_kwargs=dict(net_arch=[8])).save(tmp_path / "dacerf")
    DACER("MlpPolicy", "Pendulum-v1", buffer_size=1, policy_kwargs=dict(net_arch=[8], n_diffusion_steps=2)).save(
        tmp_path / "dacer"
    )
    with pytest.raises(ValueError, match=r"sac(\.zip)? holds a SAC model .*not a DACERF model: load it with SAC\.load"):
        DACERF.load(tmp_path / "sac")
    with pytest.raises(ValueError, match=r"holds a DACER model .*load it with DACER\.load"):
        DACERF.load(tmp_path / "dacer.zip")
    with pytest.raises(ValueError, match=r"holds a DACERF model .*load it with DACERF\.load"):
        DACER.load(tmp_path / "dacerf.zip")
    # a file that is not a model at all still gets SB3's own error
    (tmp_path / "junk.zip").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="wasn't a zip-file"):
        DACERF.load(tmp_path / "junk.zip")


def test_learn_warns_when_no_gradient_step_was_taken(model_class, fast):
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    message = r"learn\(\) took 40 environment steps without a single gradient step.*learning_starts=50"
    with pytest.warns(UserWarning, match=message):
        model.learn(40)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.learn(30, reset_num_timesteps=False)  # past learning_starts now: gradient steps, no warning


def test_short_run_writes_its_train_scalars_to_tensorboard(tmp_path, model_class, fast):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    # 150 steps: fewer than log_interval=4 Pendulum episodes, so SB3 alone would never write the logs
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, tensorboard_log=str(tmp_path), **fast)
    model.learn(150)
    (run,) = tmp_path.glob(f"{model_class.__name__}_1")
    events = EventAccumulator(str(run))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"train/critic_loss", "train/actor_loss", "train/n_updates"} <= tags
    assert events.Scalars("train/n_updates")[-1].value == 100
    assert events.Scalars("train/n_updates")[-1].step == 150


@ONLY_DACERF
def test_pickled_buffer_is_a_plain_replay_buffer(tmp_path, model_class, fast):
    # what atomic saving writes is exactly SB3's format: the buffer unpickles without this package's help
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, **{**fast, "learning_starts": 10})
    model.learn(20)
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    with open(tmp_path / "buffer.pkl", "rb") as file:
        assert type(pickle.load(file)).__name__ == "ReplayBuffer"
