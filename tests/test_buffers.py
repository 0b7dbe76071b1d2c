"""DemonstrationReplayBuffer: demonstrations kept apart, a fixed share of every batch drawn from them."""

import numpy as np
import pytest
from gymnasium import spaces

from sb3_dacerf.common.buffers import DemonstrationReplayBuffer

OBSERVATIONS = spaces.Box(-10, 10, (3,), np.float32)
ACTIONS = spaces.Box(-1, 1, (2,), np.float32)


def fill(buffer: DemonstrationReplayBuffer, n: int, reward: float) -> None:
    for _ in range(n):
        obs = np.full((1, 3), reward, np.float32)
        buffer.add(obs, obs, np.zeros((1, 2), np.float32), np.array([reward]), np.array([False]), [{}])


def test_demonstrations_are_kept_apart_and_get_their_share_of_each_batch():
    buffer = DemonstrationReplayBuffer(50, OBSERVATIONS, ACTIONS, device="cpu", demonstration_fraction=0.25)
    fill(buffer, 10, reward=0.0)  # the agent's own
    with buffer.recording_demonstrations():
        fill(buffer, 7, reward=1.0)
    fill(buffer, 100, reward=0.0)  # wraps the agent's part twice; the demonstrations stay
    assert buffer.size() == 50 and buffer.full and buffer.n_demonstrations() == 7
    for batch_size in (8, 64):
        batch = buffer.sample(batch_size)
        n = round(0.25 * batch_size)
        assert batch.rewards.shape == (batch_size, 1) and batch.observations.shape == (batch_size, 3)
        np.testing.assert_array_equal(batch.rewards[:n].numpy(), 1.0)
        np.testing.assert_array_equal(batch.rewards[n:].numpy(), 0.0)
        np.testing.assert_array_equal(batch.next_observations[:n].numpy(), 1.0)


def test_one_empty_part_gives_the_whole_batch_to_the_other():
    buffer = DemonstrationReplayBuffer(50, OBSERVATIONS, ACTIONS, device="cpu", demonstration_fraction=0.5)
    with buffer.recording_demonstrations():
        fill(buffer, 5, reward=1.0)
    assert buffer.size() == 0
    np.testing.assert_array_equal(buffer.sample(16).rewards.numpy(), 1.0)
    plain = DemonstrationReplayBuffer(50, OBSERVATIONS, ACTIONS, device="cpu", demonstration_fraction=0.5)
    fill(plain, 5, reward=0.0)
    np.testing.assert_array_equal(plain.sample(16).rewards.numpy(), 0.0)


@pytest.mark.parametrize("fraction", [-0.1, 1.5])
def test_a_share_outside_zero_one_is_refused(fraction):
    with pytest.raises(ValueError, match=r"demonstration_fraction .* must be in \[0, 1\]"):
        DemonstrationReplayBuffer(50, OBSERVATIONS, ACTIONS, demonstration_fraction=fraction)


def test_scripted_demonstrations_go_to_their_part_and_survive_save_and_load(tmp_path):
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from sb3_dacerf import DACERF
    from sb3_dacerf.common.demonstrations import add_scripted_transitions

    env_fn = lambda: gym.make("DACERF-Intersection-v0", config={"duration": 5})  # noqa: E731
    vec_env = VecNormalize(DummyVecEnv([env_fn]), norm_reward=False)
    model = DACERF(
        "MlpPolicy",
        vec_env,
        seed=0,
        learning_starts=10,
        batch_size=16,
        replay_buffer_class=DemonstrationReplayBuffer,
        replay_buffer_kwargs=dict(demonstration_fraction=0.5, demonstration_size=100),
    )
    add_scripted_transitions(model, 60)
    buffer = model.replay_buffer
    assert buffer.n_demonstrations() == 60 and buffer.size() == 0 and model.num_timesteps == 0
    with pytest.raises(ValueError, match=r"do not fit in the 40 free places .* larger demonstration_size"):
        add_scripted_transitions(model, 41)
    assert buffer.n_demonstrations() == 60  # nothing was added
    model.learn(30)
    assert buffer.size() == 30 and buffer.n_demonstrations() == 60
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    fresh = DACERF("MlpPolicy", vec_env, replay_buffer_class=DemonstrationReplayBuffer)
    fresh.load_replay_buffer(tmp_path / "buffer.pkl")
    loaded = fresh.replay_buffer
    assert loaded.n_demonstrations() == 60 and loaded.size() == 30 and loaded.demonstration_fraction == 0.5
    np.testing.assert_array_equal(loaded.demonstrations.actions[:60], buffer.demonstrations.actions[:60])


def test_dacerf_fits_the_demonstrated_actions_with_demonstration_targets_actions():
    """demonstration_targets="actions": the batch's leading demonstrations are fitted as they are, at the mean weight."""
    import torch as th

    from sb3_dacerf import DACERF

    buffer_kwargs = dict(demonstration_fraction=0.25, demonstration_targets="actions")
    kwargs = dict(replay_buffer_class=DemonstrationReplayBuffer, replay_buffer_kwargs=buffer_kwargs)
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, learning_starts=20, batch_size=32, **kwargs)
    with model.replay_buffer.recording_demonstrations():
        model.learn(40)  # transitions of the untrained policy, standing in for demonstrations
    model.learn(40)
    buffer = model.replay_buffer
    assert buffer.n_demonstrations() == 40 and buffer.size() == 40
    batch = buffer.sample(32, env=None)
    assert batch.n_demonstrations == 8
    terms = model.actor_loss_terms(batch)
    th.testing.assert_close(terms["targets"][:8], batch.actions[:8])
    assert not th.allclose(terms["targets"][8:], batch.actions[8:])  # the agent's own: Langevin targets
    assert th.allclose(terms["lambda_f"][:8], terms["lambda_f"][:8].mean().expand(8, 1))
    buffer.demonstration_targets = "langevin"  # the paper's update: every replay action moved by Langevin dynamics
    batch = buffer.sample(32, env=None)
    assert not th.allclose(model.actor_loss_terms(batch)["targets"][:8], batch.actions[:8])
    with pytest.raises(ValueError, match="demonstration_targets='copy': it must be 'langevin' or 'actions'"):
        DACERF(
            "MlpPolicy",
            "Pendulum-v1",
            replay_buffer_class=DemonstrationReplayBuffer,
            replay_buffer_kwargs=dict(demonstration_targets="copy"),
        )
