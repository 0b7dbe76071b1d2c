"""The flow actor as a conditional generative model, trained by flow matching alone."""

import copy
import functools

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from torch import nn

from sb3_dacerf.dacerf.dacerf import flow_matching_loss
from sb3_dacerf.dacerf.policies import FlowActor


def make_flow_actor(n_sampling_steps: int, obs_dim: int = 2) -> FlowActor:
    observation_space = spaces.Box(-1, 1, (obs_dim,), np.float32)
    return FlowActor(
        observation_space,
        spaces.Box(-1, 1, (1,), np.float32),
        net_arch=[128, 128],
        features_extractor=nn.Flatten(),
        features_dim=obs_dim,
        n_sampling_steps=n_sampling_steps,
    )


def fit_two_modes(field: FlowActor, n_updates: int = 1500) -> None:
    """Conditional flow matching towards a target that is ±0.6 for state s0 and ±0.2 + 0.5 for state s1."""
    optimizer = th.optim.Adam(field.parameters(), lr=2e-3)
    for _ in range(n_updates):
        states = th.randint(0, 2, (256,))
        features = nn.functional.one_hot(states, 2).float()
        sign = th.randint(0, 2, (256, 1)).float() * 2 - 1
        targets = th.where(states[:, None] == 0, 0.6 * sign, 0.5 + 0.2 * sign)
        loss = flow_matching_loss(functools.partial(field.velocity, features), targets).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


@pytest.fixture(scope="module")
def trained_field() -> FlowActor:
    """Trained once for the module: tests take a copy with :func:`with_sampling_steps` and leave it unchanged."""
    th.manual_seed(0)
    field = make_flow_actor(n_sampling_steps=1)
    fit_two_modes(field)
    return field


def with_sampling_steps(field: FlowActor, n_sampling_steps: int) -> FlowActor:
    """A copy of ``field`` that samples with ``n_sampling_steps`` Euler steps."""
    field = copy.deepcopy(field)
    field.n_sampling_steps = n_sampling_steps
    return field


@pytest.mark.parametrize("state, modes", [(0, (-0.6, 0.6)), (1, (0.3, 0.7))])
def test_multi_step_sampling_finds_both_modes(trained_field, state, modes):
    field = with_sampling_steps(trained_field, 20)
    features = nn.functional.one_hot(th.full((2000,), state), 2).float()
    with th.no_grad():
        actions = field.sample(features, th.randn((2000, 1))).squeeze(1)
    for mode in modes:
        assert (actions - mode).abs().lt(0.1).float().mean() > 0.3, f"mode {mode} missing"
    # and little mass half-way between the modes
    assert (actions - sum(modes) / 2).abs().lt(0.05).float().mean() < 0.1


def test_one_step_sampling_collapses_to_the_conditional_mean(trained_field):
    """With one Euler step, v(s, a0, 0) ≈ E[a*|s] - a0 under independent coupling: a1 ≈ E[a*|s] for every a0."""
    field = with_sampling_steps(trained_field, 1)
    features = nn.functional.one_hot(th.zeros(2000, dtype=th.long), 2).float()
    with th.no_grad():
        actions = field.sample(features, th.randn((2000, 1))).squeeze(1)
    assert abs(actions.mean().item()) < 0.1
    assert actions.std().item() < 0.2  # far below the target's 0.6 spread


def test_deterministic_forward_starts_from_the_prior_mean():
    th.manual_seed(0)
    field = make_flow_actor(n_sampling_steps=3)
    observations = th.rand((5, 2))
    assert th.equal(field(observations, deterministic=True), field(observations, deterministic=True))
    assert not th.equal(field(observations), field(observations))
    features = field.extract_features(observations, field.features_extractor)
    assert th.equal(field(observations, deterministic=True), field.sample(features, th.zeros((5, 1))))
    assert field(observations * 100).abs().max() <= 1.0
