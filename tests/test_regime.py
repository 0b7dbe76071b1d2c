"""sb3_dacerf.common.regime: environment steps per gradient step in SB3's terms, and GOPS's trainer translated."""

from fractions import Fraction

import pytest
import torch
from stable_baselines3 import SAC

from sb3_dacerf.common.regime import (
    gops_off_serial_to_sb3,
    steps_per_gradient_kwargs,
    transitions_per_rollout,
)


@pytest.mark.parametrize(
    ("steps", "n_envs", "expected"),
    [
        ("1", 1, dict(train_freq=1, gradient_steps=1)),
        ("200", 1, dict(train_freq=200, gradient_steps=1)),
        ("200", 4, dict(train_freq=50, gradient_steps=1)),
        ("16", 16, dict(train_freq=1, gradient_steps=1)),
        ("1/4", 1, dict(train_freq=1, gradient_steps=4)),
        ("0.5", 2, dict(train_freq=1, gradient_steps=4)),
        (Fraction(1, 3), 1, dict(train_freq=1, gradient_steps=3)),
    ],
)
def test_steps_per_gradient_kwargs(steps, n_envs, expected):
    kwargs = steps_per_gradient_kwargs(steps, n_envs)
    assert kwargs == expected
    # S = train_freq * n_envs / gradient_steps
    assert Fraction(kwargs["train_freq"] * n_envs, kwargs["gradient_steps"]) == Fraction(str(steps))
    assert transitions_per_rollout(steps, n_envs) == kwargs["train_freq"] * n_envs
    assert transitions_per_rollout(None, n_envs) == n_envs


@pytest.mark.parametrize(
    ("steps", "n_envs", "message"),
    [
        ("0", 1, "must be positive"),
        ("-2", 1, "must be positive"),
        ("many", 1, "is not a number"),
        ("1/0", 1, "is not a number"),
        ("2.5", 1, "above 1 it must be a whole number"),
        ("0.3", 1, "below 1 it must be 1/G"),
        ("2/3", 1, "below 1 it must be 1/G"),
        ("10", 4, r"not a multiple of n_envs 4: .* use n_envs in \[1, 2, 5, 10\]"),
        ("4", 0, "n_envs must be at least 1"),
    ],
)
def test_steps_per_gradient_refuses_what_does_not_fit(steps, n_envs, message):
    with pytest.raises(ValueError, match=message):
        steps_per_gradient_kwargs(steps, n_envs)


def test_gops_settings_of_the_paper():
    """The paper's table (sample batch 200, replay batch 512, 5e5 iterations) with GOPS's example warm-up."""
    settings = gops_off_serial_to_sb3(200, 512, 500_000, buffer_warm_size=10_000, n_envs=4)
    assert settings == dict(
        n_envs=4,
        train_freq=50,
        gradient_steps=1,
        batch_size=512,
        learning_starts=10_000,
        total_timesteps=10_000 + 200 * 500_000,
        total_gradient_steps=500_000,
        steps_per_gradient=Fraction(200),
    )
    # a sampling every 4 iterations: 50 transitions per gradient step; the warm-up is whole sample batches
    settings = gops_off_serial_to_sb3(200, 512, 1_000, buffer_warm_size=150, sample_interval=4)
    assert settings["steps_per_gradient"] == 50 and settings["gradient_steps"] == 4
    assert settings["learning_starts"] == 200 and settings["total_timesteps"] == 200 + 250 * 200
    with pytest.raises(ValueError, match="sample_batch_size 200 is not a multiple of n_envs 3"):
        gops_off_serial_to_sb3(200, 512, 10, n_envs=3)
    with pytest.raises(ValueError, match="max_iteration must be at least 1"):
        gops_off_serial_to_sb3(200, 512, 0)


def test_sb3_makes_the_gradient_steps_gops_makes():
    """An SB3 run with the translated settings makes GOPS's number of gradient steps on GOPS's transitions."""
    torch.set_num_threads(1)
    settings = gops_off_serial_to_sb3(8, 16, 20, buffer_warm_size=20, sample_interval=2, n_envs=2)
    from stable_baselines3.common.env_util import make_vec_env

    env = make_vec_env("Pendulum-v1", n_envs=settings["n_envs"], seed=0)
    keys = ("train_freq", "gradient_steps", "batch_size", "learning_starts")
    model = SAC("MlpPolicy", env, policy_kwargs=dict(net_arch=[8]), seed=0, **{k: settings[k] for k in keys})
    model.learn(settings["total_timesteps"])
    assert model.num_timesteps == settings["total_timesteps"] == 24 + 10 * 8
    assert model._n_updates == settings["total_gradient_steps"] == 20
