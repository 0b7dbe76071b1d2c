import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import autograd_action_gradient
from stable_baselines3.common.torch_layers import FlattenExtractor
from torch import nn

from sb3_dacerf.common.policies import BatchRenormCritic, EnsembleBatchRenorm, EnsembleCritic, EnsembleLayerNorm, LayerNormCritic
from sb3_dacerf.common.twin_critic import frozen
from sb3_dacerf.dacerf.dacerf import langevin_targets
from sb3_dacerf.dacerf.policies import ACTIVATION_BACKWARDS, MinQActionGradient


def quadratic_q(mean: th.Tensor):
    """Q(a) = -||a - mean||² / 2, whose Boltzmann density exp(Q / α) is N(mean, α I)."""
    return lambda actions: -0.5 * (actions - mean).pow(2).sum(dim=1, keepdim=True)


def quadratic_gradient(mean: th.Tensor):
    """∇_a of :func:`quadratic_q`, by autograd."""
    return autograd_action_gradient(quadratic_q(mean))


def test_quadratic_energy_gives_gaussian_of_mean_mu_and_variance_alpha():
    th.manual_seed(0)
    n_samples, step_size, temperature = 20_000, 0.01, 0.05
    mean = th.tensor([0.3, -0.2])
    start = th.zeros((n_samples, 2))
    samples = langevin_targets(quadratic_gradient(mean), start, n_steps=1500, step_size=step_size, temperature=temperature)
    # Unadjusted Langevin on this energy has stationary variance 2α / (2 - η), 0.5 % above α here (the clip to [-1, 1]
    # is more than 3 standard deviations from the mean)
    expected_variance = 2 * temperature / (2 - step_size)
    sample_mean = samples.mean(dim=0)
    sample_variance = samples.var(dim=0)
    # 5 standard errors of the mean and of the variance estimator
    assert th.allclose(sample_mean, mean, atol=5 * np.sqrt(expected_variance / n_samples))
    assert th.allclose(sample_variance, th.full((2,), expected_variance), atol=5 * expected_variance * np.sqrt(2 / n_samples))
    # and the bias-free target α itself within 2 %
    assert th.allclose(sample_variance, th.full((2,), temperature), rtol=0.02)


def test_targets_stay_in_bounds_and_climb_q():
    th.manual_seed(1)
    start = th.rand((512, 3)) * 2 - 1
    q_function = quadratic_q(th.tensor([5.0, -5.0, 0.0]))  # optimum outside the box
    targets = langevin_targets(autograd_action_gradient(q_function), start, n_steps=20, step_size=0.03, temperature=0.01)
    assert targets.min() >= -1.0 and targets.max() <= 1.0
    assert (q_function(targets) > q_function(start)).float().mean() > 0.95
    assert not targets.requires_grad


def test_zero_steps_returns_the_start_actions():
    start = th.rand((8, 2))
    assert th.equal(langevin_targets(quadratic_gradient(th.zeros(2)), start, n_steps=0, step_size=0.03, temperature=0.01), start)


def test_gradients_reach_actions_only():
    th.manual_seed(2)
    critic = th.nn.Sequential(th.nn.Linear(4, 16), th.nn.ReLU(), th.nn.Linear(16, 1))
    observations = th.randn((32, 2))
    start = th.rand((32, 2)) * 2 - 1
    with frozen(critic.parameters()):
        q_function = lambda a: critic(th.cat([observations, a], dim=1))  # noqa: E731
        targets = langevin_targets(autograd_action_gradient(q_function), start, 20, 0.03, 0.01)
    assert all(param.grad is None for param in critic.parameters())
    assert all(param.requires_grad for param in critic.parameters())
    assert not th.equal(targets, start)


@pytest.mark.parametrize("temperature", [0.0, 0.01])
def test_zero_temperature_is_deterministic_gradient_ascent(temperature):
    start = th.zeros((4, 1))
    first = langevin_targets(quadratic_gradient(th.ones(1)), start, 10, 0.1, temperature)
    second = langevin_targets(quadratic_gradient(th.ones(1)), start, 10, 0.1, temperature)
    assert th.equal(first, second) == (temperature == 0.0)


def make_critic(
    activation_fn: type[nn.Module],
    observation_dim: int = 5,
    action_dim: int = 3,
    n_critics: int = 2,
    layer_norm: bool = False,
    batch_renorm: bool = False,
):
    observation_space = gym.spaces.Box(-1, 1, (observation_dim,))
    action_space = gym.spaces.Box(-1, 1, (action_dim,))
    critic_class = LayerNormCritic if layer_norm else BatchRenormCritic if batch_renorm else EnsembleCritic
    return critic_class(
        observation_space,
        action_space,
        net_arch=[32, 16],
        features_extractor=FlattenExtractor(observation_space),
        features_dim=observation_dim,
        activation_fn=activation_fn,
        n_critics=n_critics,
    )


@pytest.mark.parametrize("normalisation", [None, "layer_norm", "batch_renorm"])
@pytest.mark.parametrize("n_critics", [1, 2, 3])
@pytest.mark.parametrize("activation_fn", list(ACTIVATION_BACKWARDS))
def test_min_q_gradient_matches_autograd_through_min(activation_fn, n_critics, normalisation):
    """The written-out gradient (every activation it covers; without normalisation, with LayerNorm, or with batch
    renormalisation in running-statistics mode) equals autograd of min_j Q_j."""
    if normalisation == "batch_renorm":
        pytest.importorskip("sb3_contrib")
    th.manual_seed(3)
    critic = make_critic(
        activation_fn,
        n_critics=n_critics,
        layer_norm=normalisation == "layer_norm",
        batch_renorm=normalisation == "batch_renorm",
    )
    for module in critic.modules():
        if isinstance(module, EnsembleLayerNorm):  # away from LayerNorm's initial γ = 1, β = 0
            nn.init.normal_(module.weight, 1.0, 0.3)
            nn.init.normal_(module.bias, 0.0, 0.3)
        if isinstance(module, EnsembleBatchRenorm):  # and from batch renormalisation's initial statistics
            nn.init.normal_(module.scale, 1.0, 0.3)
            nn.init.normal_(module.bias, 0.0, 0.3)
            module.ra_mean.normal_(0.0, 0.5)
            module.ra_var.uniform_(0.5, 2.0)
    observations, actions = th.randn((64, 5)), th.rand((64, 3)) * 2 - 1
    gradient = MinQActionGradient(critic, observations)

    def min_q(a):
        return th.min(th.cat(critic(observations, a), dim=1), dim=1, keepdim=True).values

    with frozen(critic.parameters()):
        expected = autograd_action_gradient(min_q)(actions)
        assert th.allclose(gradient(actions), expected, atol=1e-6)
        # the first call kept min_j Q_j at its actions, and a forward pass alone gives the same values
        assert th.allclose(gradient.start_min_q, min_q(actions), atol=1e-6)
        assert th.allclose(gradient.min_q(actions), min_q(actions), atol=1e-6)
        # and the whole loop, with the same noise
        th.manual_seed(4)
        targets = langevin_targets(gradient, actions, 20, 0.03, 0.01)
        th.manual_seed(4)
        assert th.allclose(targets, langevin_targets(autograd_action_gradient(min_q), actions, 20, 0.03, 0.01), atol=1e-5)
    assert all(param.grad is None for param in critic.parameters())


@pytest.mark.parametrize("case", ["ties", "one_critic_lowest"])
def test_min_q_gradient_on_ties_and_when_one_critic_is_always_lowest(case):
    """Per sample the written-out gradient is the first smallest critic's, as autograd through th.min: with equal
    critics (every sample a tie) that is the first critic's, and a critic that is lowest everywhere leaves the other's
    group empty."""
    th.manual_seed(5)
    critic = make_critic(nn.ReLU, n_critics=2, layer_norm=True)
    output = critic.ensemble[-1]
    with th.no_grad():
        if case == "ties":
            for param in critic.ensemble.parameters():
                param[1].copy_(param[0])
        else:
            output.bias[1] = output.bias[0] - 1e3
    observations, actions = th.randn((32, 5)), th.rand((32, 3)) * 2 - 1
    lowest = 1 if case == "one_critic_lowest" else 0
    gradient = MinQActionGradient(critic, observations)
    with frozen(critic.parameters()):
        expected = autograd_action_gradient(lambda a: critic.q_values(observations, a)[lowest])(actions)
        assert th.allclose(gradient(actions), expected, atol=1e-6)


def test_min_q_gradient_refuses_what_it_does_not_cover():
    """Another activation, or batch renormalisation in training mode, is a clear error (the model never builds them)."""
    with pytest.raises(ValueError, match="Langevin gradient is written out for"):
        MinQActionGradient(make_critic(nn.Softplus), th.randn((4, 5)))
    pytest.importorskip("sb3_contrib")
    critic = make_critic(nn.ReLU, batch_renorm=True)
    critic.set_bn_training_mode(True)
    with pytest.raises(ValueError, match="running-statistics mode"):
        MinQActionGradient(critic, th.randn((4, 5)))
