"""DACER-F's entropy regulator (exploration noise 0.15·α, α learned) and the weighting of the actor loss."""

import math

import numpy as np
import pytest
import torch as th

from sb3_dacerf import DACERF
from sb3_dacerf.dacerf.dacerf import FLOW_MATCHING_WEIGHTS, actor_loss_weights


@pytest.fixture
def model_class() -> type:
    """This module's algorithm, for the ``fast`` settings of conftest.py."""
    return DACERF


def observations(model: DACERF, n: int = 16) -> th.Tensor:
    return th.as_tensor(np.stack([model.observation_space.sample() for _ in range(n)]))


@pytest.mark.parametrize("ent_coef", [0.5, 2.0])
def test_noise_scale_follows_alpha(ent_coef, fast):
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, ent_coef=ent_coef, **fast)
    obs = observations(model)
    features = model.actor.extract_features(obs, model.actor.features_extractor)
    th.manual_seed(7)
    noisy = model.actor(obs)
    th.manual_seed(7)
    a0 = th.randn((len(obs), 1))
    xi = th.randn((len(obs), 1))
    expected = (model.actor.sample(features, a0) + 0.15 * ent_coef * xi).clamp(-1, 1)
    assert math.isclose(model.actor.exploration_std.item(), 0.15 * ent_coef, rel_tol=1e-6)
    th.testing.assert_close(noisy, expected)


def test_no_noise_with_ent_coef_zero_and_deterministic_predict_unchanged_by_alpha(fast):
    quiet = DACERF("MlpPolicy", "Pendulum-v1", seed=0, ent_coef=0.0, **fast)
    obs = observations(quiet)
    features = quiet.actor.extract_features(obs, quiet.actor.features_extractor)
    th.manual_seed(3)
    actions = quiet.actor(obs)
    th.manual_seed(3)
    th.testing.assert_close(actions, quiet.actor.sample(features, th.randn((len(obs), 1))))

    deterministic = quiet.predict(obs.numpy(), deterministic=True)[0]
    quiet.actor.log_alpha.fill_(math.log(5.0))  # a large α changes stochastic actions only
    np.testing.assert_array_equal(quiet.predict(obs.numpy(), deterministic=True)[0], deterministic)
    assert not np.allclose(quiet.predict(obs.numpy(), deterministic=False)[0], deterministic)


@pytest.mark.parametrize("direction", [1, -1])
def test_alpha_moves_towards_the_target_entropy(direction, fast):
    # A target far above (below) any entropy the policy has: α can only grow (shrink)
    model = DACERF(
        "MlpPolicy",
        "Pendulum-v1",
        seed=0,
        ent_coef="auto_1",
        target_entropy=10.0 * direction,
        policy_delay=1,
        **fast,
    )
    model.learn(150)
    alpha = model.actor.log_alpha.exp().item()
    assert (alpha - 1.0) * direction > 0.02
    assert model.logger.name_to_value["train/ent_coef"] == pytest.approx(alpha)
    assert "train/ent_coef_loss" in model.logger.name_to_value and "train/entropy" in model.logger.name_to_value


def test_fixed_alpha_is_not_learned(fast):
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, ent_coef=0.7, **fast)
    model.learn(120)
    assert model.ent_coef_optimizer is None
    assert model.actor.log_alpha.exp().item() == pytest.approx(0.7)


def test_save_and_load_restore_alpha_and_its_optimizer(tmp_path, fast):
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, policy_delay=1, **fast)
    model.learn(120)
    assert model.actor.log_alpha.item() != pytest.approx(math.log(3.0))  # learned away from α = 3
    model.save(tmp_path / "model.zip")
    loaded = DACERF.load(tmp_path / "model.zip")
    assert loaded.actor.log_alpha.item() == model.actor.log_alpha.item()
    saved_state, loaded_state = model.ent_coef_optimizer.state_dict(), loaded.ent_coef_optimizer.state_dict()
    for key in ("step", "exp_avg", "exp_avg_sq"):
        th.testing.assert_close(loaded_state["state"][0][key], saved_state["state"][0][key])
    assert loaded.ent_coef_optimizer.param_groups[0]["params"][0] is loaded.actor.log_alpha
    loaded.set_env(model.get_env())
    loaded.learn(20, reset_num_timesteps=False)  # and it goes on learning


def test_paper_mechanism_has_no_noise_and_no_alpha_update(fast):
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, ent_coef=0, **fast)
    model.learn(120)
    assert model.actor.exploration_std.item() == 0.0
    assert model.logger.name_to_value["train/ent_coef"] == 0.0


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(ent_coef="automatic"), "ent_coef"),
        (dict(ent_coef="auto_-1"), "ent_coef"),
        (dict(ent_coef=-0.1), "ent_coef"),
        (dict(ent_coef=float("inf")), "ent_coef"),
        (dict(target_entropy="high"), "target_entropy"),
        (dict(flow_matching_weights="advantage"), "flow_matching_weights='advantage': it must be one of gain, paper"),
    ],
)
def test_invalid_regulator_and_weighting_values_raise_clear_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        DACERF("MlpPolicy", "Pendulum-v1", **kwargs)


def random_q_values(seed: int = 0) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
    """Q(s, π(s)), Q(s, a*) and Q(s, a_B) of a batch."""
    # float64: a shift by 1600 leaves float32 Q-values too few digits for their differences
    generator = th.Generator().manual_seed(seed)
    q_buffer = th.randn((64, 1), generator=generator, dtype=th.float64) * 5 - 20
    q_star = q_buffer + th.rand((64, 1), generator=generator, dtype=th.float64) * 0.3 - 0.05
    q_pi = q_buffer + th.randn((64, 1), generator=generator, dtype=th.float64) * 0.2
    return q_pi, q_star, q_buffer


@pytest.mark.parametrize("method", ["gain", "paper"])
def test_lambda_f_is_proportional_to_the_langevin_gain_and_invariant_to_a_reward_shift(method):
    _, q_star, q_buffer = random_q_values()
    kappa, lambda_f = actor_loss_weights(method, q_star, q_buffer)
    gain = (q_star - q_buffer).clamp_min(0)
    order = gain.flatten().argsort()
    assert (lambda_f.flatten()[order].diff() >= -1e-12).all()  # more gain, more imitation
    assert (lambda_f[gain == 0] == 0).all()  # no imitation without a Langevin gain
    ratio = lambda_f[gain > 0] / gain[gain > 0]
    th.testing.assert_close(ratio, th.full_like(ratio, ratio[0].item()))  # λ_f ∝ gain
    # A shift of the reward by c shifts every Q by c / (1 - γ): "gain" and "paper" weights do not move
    shift = 1600.0
    kappa_shifted, lambda_shifted = actor_loss_weights(method, q_star + shift, q_buffer + shift)
    th.testing.assert_close(lambda_shifted, lambda_f, rtol=1e-4, atol=1e-6)
    th.testing.assert_close(kappa_shifted, kappa)


def test_gain_weighting_balance_does_not_depend_on_the_reward_scale():
    q_pi, q_star, q_buffer = random_q_values()
    kappa, lambda_f = actor_loss_weights("gain", q_star, q_buffer)
    kappa_10, lambda_10 = actor_loss_weights("gain", 10 * q_star, 10 * q_buffer)
    # -Q/κ and λ_f: the same loss for rewards ten times larger
    th.testing.assert_close(lambda_10, lambda_f)
    th.testing.assert_close(10 * q_pi / kappa_10, q_pi / kappa)
    assert set(FLOW_MATCHING_WEIGHTS) == {"gain", "paper"}


def test_paper_weighting_is_the_gain_itself_and_its_balance_does_not_depend_on_the_reward_scale():
    q_pi, q_star, q_buffer = random_q_values()
    kappa, lambda_f = actor_loss_weights("paper", q_star, q_buffer, coef=2.0)
    # λ_f = c · ReLU(Q(s, a*) - Q(s, a_B)), by hand, and no rescaling of -Q
    th.testing.assert_close(lambda_f, 2.0 * (q_star - q_buffer).clamp_min(0))
    assert kappa.item() == 1.0
    # Rewards ten times larger: -Q and λ_f both grow ten times, so the two terms keep their ratio
    kappa_10, lambda_10 = actor_loss_weights("paper", 10 * q_star, 10 * q_buffer, coef=2.0)
    th.testing.assert_close(lambda_10 / (10 * q_pi / kappa_10).abs().mean(), lambda_f / (q_pi / kappa).abs().mean())


def test_gain_weighting_stays_finite_without_any_langevin_gain():
    _, _, q_buffer = random_q_values()
    kappa, lambda_f = actor_loss_weights("gain", q_buffer - 1.0, q_buffer)
    assert th.isfinite(kappa) and kappa > 0 and (lambda_f == 0).all()


def test_actor_loss_terms_and_their_balance_are_logged(fast):
    """The balance of the actor loss's terms is a diagnostic: logged with verbose=2 only (two extra backward passes)."""
    quiet = DACERF("MlpPolicy", "Pendulum-v1", seed=0, policy_delay=1, **fast).learn(120)
    assert "train/imitation_to_improvement_grad" not in quiet.logger.name_to_value
    assert math.isfinite(quiet.logger.name_to_value["train/imitation_term"])
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, policy_delay=1, verbose=2, **fast)
    model.learn(120)
    logged = model.logger.name_to_value
    for key in ("improvement_term", "imitation_term", "improvement_scale", "lambda_f", "imitation_to_improvement_grad"):
        assert math.isfinite(logged[f"train/{key}"]), key
    assert logged["train/imitation_to_improvement_grad"] > 0
