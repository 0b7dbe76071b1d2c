"""
RL Zoo's ``ParallelTrainCallback`` with the algorithms of this package (``sb3_dacerf.zoo.ParallelTraining``): gradient
steps in a thread while the model collects, checked in-process on a tiny budget. The same callback through
``python -m rl_zoo3.train`` is in ``tests/test_zoo_upstream.py``.
"""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import CheckpointCallback

pytest.importorskip("rl_zoo3")

import rl_zoo3.callbacks
from conftest import fast_settings
from rl_zoo3.callbacks import ParallelTrainCallback

from sb3_dacerf import DACER, DACERF
from sb3_dacerf.common.validation import NonFiniteLossError
from sb3_dacerf.zoo import ParallelTraining, register

# Patched by the start-up hook when it is installed; register() is idempotent
register(rl_zoo3.callbacks)


def state(model) -> dict[str, th.Tensor]:
    return {key: value.clone() for key, value in model.policy.state_dict().items()}


@pytest.mark.parametrize("model_class", [DACERF, DACER])
def test_parallel_training_trains_syncs_and_saves(tmp_path, model_class):
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, **fast_settings(model_class))
    initial_log_alpha = model.actor.log_alpha.item()
    callback = ParallelTrainCallback(gradient_steps=20)
    checkpoints = CheckpointCallback(save_freq=150, save_path=str(tmp_path), name_prefix="checkpoint")
    model.learn(450, callback=[callback, checkpoints])

    training = vars(callback)["_sb3_dacerf_parallel_training"]
    assert isinstance(training, ParallelTraining) and not training.running
    trainer = callback._model
    assert trainer is training.trainer and trainer is not model and callback.model_class is model_class

    # Updates happened, in rounds of 20, and the model has the trainer's update count, parameters and α
    assert model.num_timesteps == 450
    assert model._n_updates == trainer._n_updates > 0 and model._n_updates % 20 == 0
    trained, received = state(trainer), state(model)
    assert trained.keys() == received.keys()
    for key in trained:
        assert th.equal(trained[key], received[key]), key
    assert model.actor.log_alpha.item() == trainer.actor.log_alpha.item() != initial_log_alpha
    # The trainer's values reached the model's logger (kept readable after learn())
    assert model.logger.name_to_value["train/n_updates"] == model._n_updates

    # The trainer trained on a copy of the replay buffer: the model's transitions up to the copy, no shared arrays
    copied, collected = trainer.replay_buffer, model.replay_buffer
    assert copied is not collected and not np.shares_memory(copied.observations, collected.observations)
    assert 0 < copied.pos <= collected.pos == 450 and not collected.full
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        assert np.array_equal(getattr(copied, name)[: copied.pos], getattr(collected, name)[: copied.pos]), name

    # The model is an ordinary one again: its own train() and save(), which writes what it learned
    assert "train" not in vars(model) and "save" not in vars(model)
    model.save(tmp_path / "model.zip")
    loaded = model_class.load(tmp_path / "model.zip")
    assert loaded.num_timesteps == 450 and loaded._n_updates == model._n_updates
    assert loaded.actor.log_alpha.item() == model.actor.log_alpha.item()
    for key, value in state(loaded).items():
        assert th.equal(value, received[key]), key
    observation = np.array([1.0, 0.0, 0.0], dtype=np.float32)
    action, _ = loaded.predict(observation, deterministic=True)
    assert action.shape == (1,) and -2.0 <= action[0] <= 2.0
    np.testing.assert_array_equal(action, model.predict(observation, deterministic=True)[0])

    # Checkpoints saved while the trainer learned: its parameters, with the model's progress
    for steps in (150, 300, 450):
        checkpoint = model_class.load(tmp_path / f"checkpoint_{steps}_steps.zip")
        assert checkpoint.num_timesteps == steps
        assert checkpoint._n_updates <= model._n_updates


class NanRewardPendulum(gym.Wrapper):
    def __init__(self):
        super().__init__(gym.make("Pendulum-v1"))

    def step(self, action):
        observation, _, terminated, truncated, info = self.env.step(action)
        return observation, float("nan"), terminated, truncated, info


def test_error_in_the_training_thread_is_raised_by_learn():
    model = DACERF("MlpPolicy", NanRewardPendulum(), seed=0, **fast_settings(DACERF))
    # A ValueError, raised in the main thread: RL Zoo's -optimize prunes the trial instead of training on silently
    with pytest.raises(NonFiniteLossError, match="non-finite rewards"):
        model.learn(300, callback=ParallelTrainCallback(gradient_steps=5))


def test_sac_keeps_rl_zoo_behaviour():
    model = SAC("MlpPolicy", "Pendulum-v1", learning_starts=50, batch_size=32, buffer_size=1_000, seed=0)
    callback = ParallelTrainCallback(gradient_steps=5)
    model.learn(200, callback=callback)
    assert "_sb3_dacerf_parallel_training" not in vars(callback)
    assert callback.model_class is SAC and callback._model._n_updates > 0


PARALLEL_YAML = """
Pendulum-v1:
  policy: 'MlpPolicy'
  n_timesteps: 400
  learning_starts: 50
  batch_size: 32
  langevin_steps: 2
  policy_kwargs: "dict(net_arch=[32, 32])"
  callback:
    - rl_zoo3.callbacks.ParallelTrainCallback:
        gradient_steps: 10
"""


@pytest.mark.slow
def test_rl_zoo_yaml_entry_with_parallel_train_callback(tmp_path):
    from test_zoo import zoo

    (tmp_path / "parallel.yml").write_text(PARALLEL_YAML)
    run_args = ["--algo", "dacerf", "--env", "Pendulum-v1", "-f", "logs"]
    options = ["--conf-file", "parallel.yml", "--num-threads", "1", "--seed", "0"]
    checkpoints = ["--eval-freq", "200", "--eval-episodes", "1", "--save-freq", "200"]
    zoo("train", *run_args, *options, *checkpoints, cwd=tmp_path)
    run = tmp_path / "logs" / "dacerf" / "Pendulum-v1_1"
    model = DACERF.load(run / "Pendulum-v1.zip")
    assert model.num_timesteps == 400 and model._n_updates > 0 and model._n_updates % 10 == 0
    assert DACERF.load(run / "rl_model_200_steps.zip").num_timesteps == 200
    assert (run / "best_model.zip").is_file()
    enjoy = zoo("enjoy", *run_args, "--exp-id", "1", "-n", "50", "--no-render", cwd=tmp_path)
    assert "Pendulum-v1_1/Pendulum-v1.zip" in enjoy.stdout
