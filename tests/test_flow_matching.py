"""The flow-matching loss of DACER-F's actor update (the imitation term of J_F), on its own."""

import pytest
import torch as th

from sb3_dacerf.dacerf.dacerf import flow_matching_loss


def test_value_on_the_straight_path():
    """||v(a_t, t) - (a* - a_0)||² with a_t = (1 - t) a_0 + t a*, written out for two samples."""
    targets = th.tensor([[1.0, 0.0], [0.5, -0.5]])
    noise = th.tensor([[-1.0, 2.0], [0.5, 0.5]])
    time = th.tensor([[0.25], [1.0]])
    seen = {}

    def velocity(actions_t, t):
        seen.update(actions_t=actions_t, t=t)
        return 2 * actions_t + t

    loss = flow_matching_loss(velocity, targets, noise=noise, time=time)
    # sample 0: a_t = (-0.5, 1.5), v = (-0.75, 3.25), a* - a_0 = (2, -2): 2.75² + 5.25²
    # sample 1: a_t = (0.5, -0.5), v = (2, 0), a* - a_0 = (0, -1): 2² + 1²
    th.testing.assert_close(seen["actions_t"], th.tensor([[-0.5, 1.5], [0.5, -0.5]]))
    assert th.equal(seen["t"], time)
    th.testing.assert_close(loss, th.tensor([[2.75**2 + 5.25**2], [5.0]]))


def test_zero_for_the_exact_velocity_and_positive_otherwise():
    targets, noise = th.randn((8, 3)), th.randn((8, 3))
    exact = flow_matching_loss(lambda a_t, t: targets - noise, targets, noise=noise)
    assert exact.shape == (8, 1) and th.all(exact == 0)
    assert th.all(flow_matching_loss(lambda a_t, t: th.zeros_like(a_t), targets, noise=noise) > 0)


def test_default_draws_are_standard_normal_noise_then_uniform_times():
    targets = th.randn((256, 2))
    inputs = []
    th.manual_seed(0)
    loss = flow_matching_loss(lambda a_t, t: inputs.append(t) or a_t, targets)
    th.manual_seed(0)
    noise, time = th.randn_like(targets), th.rand((256, 1))
    assert th.equal(loss, flow_matching_loss(lambda a_t, t: a_t, targets, noise=noise, time=time))
    assert inputs[0].shape == (256, 1) and 0 <= inputs[0].min() and inputs[0].max() <= 1


def test_minimising_it_learns_the_mean_velocity_towards_the_targets():
    """For one target a*, the best velocity that ignores a_t and t is E[a* - a_0] = a*."""
    th.manual_seed(1)
    target = th.tensor([0.6, -0.3])
    constant = th.zeros(2, requires_grad=True)
    optimizer = th.optim.SGD([constant], lr=0.2)
    for _ in range(200):
        loss = flow_matching_loss(lambda a_t, t: constant.expand_as(a_t), target.expand(4096, 2)).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert constant.detach() == pytest.approx(target.tolist(), abs=0.05)
