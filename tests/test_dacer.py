"""DACER's own behaviours; what it shares with DACERF is tested in test_algorithms.py."""

import csv
import math

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure

from sb3_dacerf import DACER
from sb3_dacerf.dacer.dacer import gaussian_mixture_entropy
from sb3_dacerf.dacer.policies import vp_betas


@pytest.fixture
def model_class() -> type:
    """This module's algorithm, for the ``fast`` settings of conftest.py."""
    return DACER


def test_logs_the_paper_quantities_on_box_observations(tmp_path, fast):
    # that it learns is checked in test_learning.py; here, that the logged quantities are there and make sense
    model = DACER("MlpPolicy", "Pendulum-v1", seed=0, alpha_update_interval=100, entropy_samples=10, **fast)
    initial_alpha = model.actor.log_alpha.exp().item()
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    with open(tmp_path / "progress.csv") as file:
        last = list(csv.DictReader(file))[-1]
    logged = {key: float(last[f"train/{key}"]) for key in ("critic_loss", "actor_loss", "ent_coef", "entropy", "n_updates")}
    assert all(math.isfinite(value) for value in logged.values()), logged
    assert logged["critic_loss"] >= 0 and logged["ent_coef"] > 0, logged
    assert logged["ent_coef"] != pytest.approx(initial_alpha)  # updated once (alpha_update_interval=100) from the entropy
    assert logged["entropy"] == pytest.approx(model.entropy)
    assert logged["n_updates"] == model._n_updates == 150


# The official JAX code, github.com/happy-yan/DACER-Diffusion-with-Online-RL at commit 848c1f2 (2025-08-14):
# relax/algorithm/dacer.py (lr=1e-4, alpha_lr=3e-2, tau=0.005, delay_update=2, delay_alpha_update=10000,
# num_samples=200), relax/network/dacer.py (log_alpha = log 3, target entropy -0.9 * act_dim, exploration noise
# 0.15 * alpha, 20 steps), relax/utils/diffusion.py (GaussianDiffusion uses vp_beta_schedule, x_T ~ N(0, I)),
# scripts/train_mujoco.py (--lr 1e-4, 3 x 256 hidden layers, Mish for DACER).
OFFICIAL_LEARNING_RATE, OFFICIAL_LOG_ALPHA = 1e-4, math.log(3.0)


def official_vp_betas(T):
    # relax/utils/diffusion.py, BetaScheduleCoefficients.vp_beta_schedule, written out with its numbers
    return np.array([1 - math.exp(-0.1 / T - 0.5 * (10.0 - 0.1) * (2 * t - 1) / T**2) for t in range(1, T + 1)])


def test_official_defaults():
    model = DACER("MlpPolicy", "Pendulum-v1")
    assert model.learning_rate == OFFICIAL_LEARNING_RATE
    assert model.actor.optimizer.param_groups[0]["lr"] == model.critic.optimizer.param_groups[0]["lr"] == 1e-4
    assert (model.tau, model.policy_delay, model.gamma) == (0.005, 2, 0.99)
    assert (model.alpha_learning_rate, model.alpha_update_interval, model.entropy_samples) == (3e-2, 10_000, 200)
    # α learned from the official log α = log 3, with its own learning rate: ent_coef="auto", as DACERF's and DSAC's
    assert model.ent_coef == "auto" and model.ent_coef_optimizer.param_groups[0]["lr"] == 3e-2
    assert model.target_entropy == pytest.approx(-0.9)
    assert model.actor.log_alpha.item() == pytest.approx(OFFICIAL_LOG_ALPHA)
    assert (model.actor.n_diffusion_steps, model.actor.exploration_noise_scale) == (20, 0.15)
    assert [m.out_features for m in model.actor.network if isinstance(m, th.nn.Linear)] == [256, 256, 256, 1]
    assert any(isinstance(m, th.nn.Mish) for m in model.actor.network)
    assert model.policy.critic.n_critics == 2


def test_vp_schedule_is_the_official_one():
    betas = vp_betas(20)
    np.testing.assert_allclose(betas, official_vp_betas(20), rtol=1e-12)
    # The first reverse step (t = T): x̂_0 = 12.5 x_T - ..., x_T kept with weight 0.78 in the posterior mean
    alphas_cumprod = np.cumprod(1 - betas)
    assert math.sqrt(1 / alphas_cumprod[-1]) == pytest.approx(12.49, abs=0.01)
    model = DACER("MlpPolicy", "Pendulum-v1")
    c0, _, _, m1, _ = model.actor.reverse_coefficients[-1]
    assert (c0, m1) == (pytest.approx(12.49, abs=0.01), pytest.approx(0.780, abs=1e-3))


def test_reverse_process_starts_from_standard_normal_noise(fast):
    model = DACER("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    starts = []
    # The noisy action x_t is the network input after the state features, the first call is at t = T
    model.actor.network.register_forward_pre_hook(lambda _, inputs: starts.append(inputs[0][:, 3:4].clone()))
    observations = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(4096)]))
    with th.no_grad():
        model.actor(observations)
    assert starts[0].std().item() == pytest.approx(1.0, abs=0.05)
    assert starts[0].mean().item() == pytest.approx(0.0, abs=0.05)


def test_one_network_call_per_diffusion_step(fast):
    model = DACER("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    calls = []
    model.actor.network.register_forward_hook(lambda *_: calls.append(1))
    model.predict(model.observation_space.sample())
    assert len(calls) == 5


def test_actor_and_targets_update_every_policy_delay_updates(fast):
    model = DACER("MlpPolicy", "Pendulum-v1", seed=0, policy_delay=2, **fast)
    model.learn(60)  # 10 updates: the last one (10) updated the actor
    actor_parameters = [param for name, param in model.actor.named_parameters() if name != "log_alpha"]  # α: its own step
    actor_before = [p.clone() for p in actor_parameters]
    target_before = [p.clone() for p in model.critic_target.parameters()]
    model.train(gradient_steps=1, batch_size=32)  # update 11: critic only
    assert all(th.equal(a, b) for a, b in zip(actor_before, actor_parameters, strict=True))
    assert all(th.equal(a, b) for a, b in zip(target_before, model.critic_target.parameters(), strict=True))
    model.train(gradient_steps=1, batch_size=32)  # update 12: actor, through all the denoising steps, and targets
    assert all(not th.equal(a, b) for a, b in zip(actor_before, actor_parameters, strict=True))
    assert not all(th.equal(a, b) for a, b in zip(target_before, model.critic_target.parameters(), strict=True))


@pytest.mark.parametrize("target_entropy, direction", [(-100.0, -1), (100.0, 1)])
def test_alpha_moves_towards_the_target_entropy_once_per_interval(target_entropy, direction, fast):
    regulator = dict(target_entropy=target_entropy, alpha_update_interval=4, entropy_samples=8)
    model = DACER("MlpPolicy", "Pendulum-v1", seed=0, **regulator, **fast)
    model.learn(59)  # updates 1..9: the entropy regulator runs at updates 1, 5 and 9
    # Adam's steps have size lr while the sign of the gradient H - H_target does not change
    assert model.actor.log_alpha.item() == pytest.approx(OFFICIAL_LOG_ALPHA + direction * 3 * 3e-2, abs=1e-4)
    assert model.ent_coef_optimizer.state_dict()["state"][0]["step"] == 3


def test_ent_coef_fixes_or_starts_alpha(tmp_path, fast):
    fixed = DACER("MlpPolicy", "Pendulum-v1", seed=0, ent_coef=0.5, alpha_update_interval=1, entropy_samples=8, **fast)
    fixed.learn(70)
    assert fixed.ent_coef_optimizer is None and fixed.actor.log_alpha.exp().item() == pytest.approx(0.5)
    assert fixed.logger.name_to_value["train/ent_coef"] == pytest.approx(0.5)
    assert DACER("MlpPolicy", "Pendulum-v1", ent_coef=0).actor.exploration_std.item() == 0.0
    assert DACER("MlpPolicy", "Pendulum-v1", ent_coef="auto_0.5").actor.log_alpha.exp().item() == pytest.approx(0.5)
    for bad in ("automatic", "auto_-1", -0.1, True):
        with pytest.raises(ValueError, match=f"Invalid ent_coef={bad!r}"):
            DACER("MlpPolicy", "Pendulum-v1", ent_coef=bad)
    with pytest.raises(TypeError, match="unexpected keyword argument 'alpha'"):
        DACER("MlpPolicy", "Pendulum-v1", alpha=0.2)


def test_gaussian_mixture_entropy_matches_closed_forms():
    th.manual_seed(0)
    gaussian = 0.3 * th.randn(16, 400, 2)
    expected = 0.5 * 2 * (1 + math.log(2 * math.pi * 0.09))
    assert gaussian_mixture_entropy(gaussian, n_components=1).mean().item() == pytest.approx(expected, abs=0.05)
    # Two well separated modes: log 2 plus the entropy of one mode
    modes = 0.6 * (2 * th.randint(0, 2, (16, 400, 1)).float() - 1) + 0.05 * th.randn(16, 400, 1)
    expected = math.log(2) + 0.5 * (1 + math.log(2 * math.pi * 0.05**2))
    assert gaussian_mixture_entropy(modes, n_components=2).mean().item() == pytest.approx(expected, abs=0.1)
    # Clipped actions (all samples on a bound) keep a finite estimate
    assert th.isfinite(gaussian_mixture_entropy(th.ones(4, 50, 3))).all()


def test_save_load_restores_the_entropy_regulator(tmp_path, fast):
    model = DACER("MlpPolicy", "Pendulum-v1", seed=0, alpha_update_interval=20, entropy_samples=8, **fast)
    model.learn(100)
    model.save(tmp_path / "dacer")
    loaded = DACER.load(tmp_path / "dacer")
    assert loaded.actor.n_diffusion_steps == 5 and loaded.policy_delay == 2
    assert loaded.actor.log_alpha.item() == model.actor.log_alpha.item() != pytest.approx(OFFICIAL_LOG_ALPHA)
    assert loaded.ent_coef_optimizer.state_dict()["state"][0]["step"] == model.ent_coef_optimizer.state_dict()["state"][0]["step"]
    assert loaded.ent_coef_optimizer.param_groups[0]["params"][0] is loaded.actor.log_alpha
    assert loaded.entropy == model.entropy


@pytest.mark.parametrize(
    "name, value",
    [("entropy_samples", 2), ("alpha_update_interval", 0), ("alpha_learning_rate", 0.0)],
)
def test_invalid_hyperparameters(name, value):
    with pytest.raises(ValueError, match=f"Invalid {name}="):
        DACER("MlpPolicy", "Pendulum-v1", **{name: value})
    with pytest.raises(ValueError, match="Invalid n_diffusion_steps=0"):
        DACER("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(n_diffusion_steps=0))


@pytest.mark.parametrize("n_diffusion_steps", [1, 5])
def test_noise_holds_the_start_and_the_posterior_noise_of_each_reverse_step(fast, n_diffusion_steps):
    fast["policy_kwargs"]["n_diffusion_steps"] = n_diffusion_steps
    model = DACER("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    actor = model.actor
    features = th.randn((8, actor.features_dim))
    th.manual_seed(1)
    noise = actor.draw_noise(features)
    assert noise.shape == (8, n_diffusion_steps, 1)
    after = th.randn(1)
    # x_T's, then the posterior noise of the steps t = T-1 .. 1, in one draw: no random number is thrown away
    th.manual_seed(1)
    assert th.equal(noise, th.randn((8, n_diffusion_steps, 1))) and th.equal(th.randn(1), after)
    # x_T = noise[:, 0]: with one step and no network output, the action is x̂_0 = x_T / sqrt(ᾱ_0)
    if n_diffusion_steps == 1:
        with th.no_grad():
            for module in actor.network.modules():
                if isinstance(module, th.nn.Linear):
                    module.weight.zero_()
                    module.bias.zero_()
            c0 = actor.reverse_coefficients[0][0]
            th.testing.assert_close(actor.sample(features, noise), (c0 * noise[:, 0]).clamp(-1, 1))
