"""DACER-F's own behaviours; what it shares with DACER is tested in test_algorithms.py."""

import csv
import math

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import BitFlippingEnv, SimpleMultiObsEnv
from stable_baselines3.common.logger import configure
from stable_baselines3.common.noise import NormalActionNoise

from sb3_dacerf import DACERF
from sb3_dacerf.common.policies import EnsembleCritic, EnsembleLinear, LayerNormCritic
from sb3_dacerf.dacerf import PAPER_HYPERPARAMETERS
from sb3_dacerf.dacerf.dacerf import langevin_targets
from sb3_dacerf.dacerf.policies import MinQActionGradient


@pytest.fixture
def model_class() -> type:
    """This module's algorithm, for the ``fast`` settings of conftest.py."""
    return DACERF


def test_logs_the_paper_quantities_on_box_observations(tmp_path, fast):
    # that it learns is checked in test_learning.py; here, that the logged quantities are there and make sense
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(300, log_interval=1)
    with open(tmp_path / "progress.csv") as file:
        last = list(csv.DictReader(file))[-1]
    keys = ("critic_loss", "actor_loss", "flow_matching_loss", "langevin_gain", "lambda_f", "action_spread", "n_updates")
    logged = {key: float(last[f"train/{key}"]) for key in keys}
    assert all(math.isfinite(value) for value in logged.values()), logged
    assert logged["critic_loss"] >= 0 and logged["flow_matching_loss"] >= 0, logged
    assert logged["lambda_f"] > 0 and logged["action_spread"] > 0, logged
    assert logged["n_updates"] == model._n_updates == 250
    assert model.actor.n_sampling_steps == 1


def test_defaults_and_paper_preset():
    model = DACERF("MlpPolicy", "Pendulum-v1")
    assert (model.tau, model.policy_delay, model.gamma) == (0.005, 3, 0.99)
    assert (model.ent_coef, model.flow_matching_weights) == ("auto", "gain")
    paper = DACERF("MlpPolicy", "Pendulum-v1", **PAPER_HYPERPARAMETERS)
    assert (paper.tau, paper.learning_rate, paper.batch_size, paper.ent_coef) == (0.001, 1e-4, 512, 0.0)
    # the paper's λ_f and data regime: 200 transitions collected per gradient step
    assert paper.flow_matching_weights == "paper"
    assert (paper.train_freq.frequency, paper.gradient_steps) == (200, 1)
    assert paper.policy.optimizer_class.__name__ == "RAD"
    assert (model.langevin_steps, model.langevin_step_size, model.langevin_temperature) == (20, 0.03, 0.01)
    assert model.actor.n_sampling_steps == 1
    assert model.policy.critic.n_critics == 2
    assert model.policy.actor is model.actor and model.policy.critic_target is model.critic_target
    # LayerNorm critics by default, SB3's MLP critics in the paper preset or on request
    assert model.policy_kwargs["critic"] == "layer_norm"
    assert isinstance(model.critic, LayerNormCritic) and isinstance(model.critic_target, LayerNormCritic)
    assert type(paper.critic) is EnsembleCritic
    mlp = DACERF("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(critic="mlp"))
    assert type(mlp.critic) is EnsembleCritic and type(mlp.critic_target) is EnsembleCritic


def test_n_step_returns_are_saved_and_loaded_without_sb3_warning_they_are_ignored(tmp_path, recwarn):
    model = DACERF("MlpPolicy", "Pendulum-v1", n_steps=3)
    assert type(model.replay_buffer) is NStepReplayBuffer and model.replay_buffer.n_steps == 3
    assert model.replay_buffer.gamma == model.gamma
    model.save(tmp_path / "nstep")
    loaded = DACERF.load(tmp_path / "nstep")
    assert loaded.n_steps == 3 and type(loaded.replay_buffer) is NStepReplayBuffer
    # SB3 warns that n_steps "is ignored" with a custom buffer class; the reloaded NStepReplayBuffer is not one
    assert not [warning for warning in recwarn if "is ignored" in str(warning.message)]
    # one-step targets by default and in the paper preset
    assert type(DACERF("MlpPolicy", "Pendulum-v1").replay_buffer) is ReplayBuffer
    assert DACERF("MlpPolicy", "Pendulum-v1", **PAPER_HYPERPARAMETERS).n_steps == 1


def test_a_model_saved_without_the_critic_setting_loads_with_mlp_critics(tmp_path):
    # files written before LayerNorm critics became the default hold MLP critics and no critic key
    model = DACERF("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(critic="mlp"), seed=0)
    del model.policy_kwargs["critic"]
    model.save(tmp_path / "old")
    loaded = DACERF.load(tmp_path / "old")
    assert type(loaded.critic) is EnsembleCritic and "critic" not in loaded.policy_kwargs
    for name, value in model.policy.state_dict().items():
        assert th.equal(value, loaded.policy.state_dict()[name]), name
    # and a model saved now keeps its LayerNorm critics
    DACERF("MlpPolicy", "Pendulum-v1", seed=0).save(tmp_path / "new")
    assert isinstance(DACERF.load(tmp_path / "new").critic, LayerNormCritic)


def test_policy_delay_updates_the_actor_every_third_critic_update(fast):
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, policy_delay=3, **fast)
    model.learn(60)  # fill the buffer past learning_starts
    actor_before = [p.clone() for p in model.actor.parameters()]
    critic_before = [p.clone() for p in model.critic.parameters()]
    model.train(gradient_steps=2, batch_size=32)  # updates 11 and 12: only 12 is an actor update
    model._n_updates = 13
    model.train(gradient_steps=1, batch_size=32)  # update 14: critic only
    assert not all(th.equal(a, b) for a, b in zip(critic_before, model.critic.parameters(), strict=True))
    changed = [not th.equal(a, b) for a, b in zip(actor_before, model.actor.parameters(), strict=True)]
    assert all(changed)
    actor_after = [p.clone() for p in model.actor.parameters()]
    model.train(gradient_steps=1, batch_size=32)  # update 15: actor update
    assert not th.equal(actor_after[0], next(model.actor.parameters()))


def test_her_replay_buffer(fast):
    env = BitFlippingEnv(n_bits=4, continuous=True, max_steps=4)
    model = DACERF(
        "MultiInputPolicy",
        env,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs=dict(n_sampled_goal=2, goal_selection_strategy="future"),
        seed=0,
        **fast,
    )
    model.learn(150)
    assert model.replay_buffer.size() > 0 and model._n_updates > 0


def test_vec_env_train_freq_gradient_steps_and_action_noise(fast):
    env = make_vec_env("Pendulum-v1", n_envs=2, seed=0)
    noise = NormalActionNoise(np.zeros(1), 0.1 * np.ones(1))
    model = DACERF("MlpPolicy", env, train_freq=(2, "step"), gradient_steps=3, action_noise=noise, seed=0, **fast)
    model.learn(200)
    assert model.num_timesteps == 200
    # one rollout = 2 steps x 2 envs; 3 gradient steps after each rollout that ends past learning_starts
    assert model._n_updates == 3 * sum(1 for timesteps in range(4, 201, 4) if timesteps > 50)


def test_shared_features_extractor_and_separate_net_arch():
    model = DACERF(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=dict(net_arch=dict(pi=[16], qf=[24, 24]), share_features_extractor=True),
        seed=0,
        learning_starts=50,
        batch_size=16,
    )
    assert model.critic.features_extractor is model.actor.features_extractor
    assert [m.out_features for m in model.actor.network if isinstance(m, th.nn.Linear)] == [16, 1]
    assert [m.out_features for m in model.critic.ensemble if isinstance(m, EnsembleLinear)] == [24, 24, 1]
    model.learn(100)


def test_save_load_restores_the_settings_and_the_optimizer(tmp_path, fast):
    fast["policy_kwargs"]["n_sampling_steps"] = 2
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    model.learn(120)
    model.save(tmp_path / "dacerf")
    loaded = DACERF.load(tmp_path / "dacerf")
    assert loaded.actor.n_sampling_steps == 2
    assert (loaded.langevin_steps, loaded.policy_delay, loaded.tau) == (20, 3, 0.005)
    for key, value in model.actor.optimizer.state_dict()["state"][0].items():
        assert th.equal(value, loaded.actor.optimizer.state_dict()["state"][0][key])


def test_resumed_training_with_saved_replay_buffer(tmp_path, fast):
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    model.learn(100)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    size = model.replay_buffer.size()

    loaded = DACERF.load(tmp_path / "model", env=gym.make("Pendulum-v1"))
    loaded.load_replay_buffer(tmp_path / "buffer")
    assert loaded.replay_buffer.size() == size
    n_updates = loaded._n_updates
    loaded.learn(50, reset_num_timesteps=False)
    assert loaded.num_timesteps == 150
    assert loaded._n_updates == n_updates + 50


# SB3's progress bar is tqdm's rich bar, which tqdm calls experimental
@pytest.mark.filterwarnings("ignore::tqdm.TqdmExperimentalWarning")
def test_callbacks_and_tensorboard(tmp_path, fast):
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, tensorboard_log=str(tmp_path / "tb"), **fast)
    model.learn(100, callback=CheckpointCallback(save_freq=50, save_path=str(tmp_path / "ckpt")), progress_bar=True)
    assert len(list((tmp_path / "ckpt").glob("*.zip"))) == 2
    assert list((tmp_path / "tb").glob("DACERF_1/events.out.tfevents.*"))


@pytest.mark.parametrize("optimizer_class", ["RAD", "rad"])
def test_rad_optimizer_by_name_and_class(optimizer_class, tmp_path):
    from rad.optim import RAD

    model = DACERF(
        "MlpPolicy",
        "Pendulum-v1",
        policy_kwargs=dict(net_arch=[32], optimizer_class=optimizer_class, optimizer_kwargs=dict(zeta=1.0)),
        learning_starts=50,
        batch_size=16,
    )
    assert isinstance(model.actor.optimizer, RAD) and model.actor.optimizer.defaults["zeta"] == 1.0
    model.learn(80)
    model.save(tmp_path / "rad")
    assert isinstance(DACERF.load(tmp_path / "rad").critic.optimizer, RAD)
    assert isinstance(DACERF("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(optimizer_class=RAD)).critic.optimizer, RAD)


def test_missing_rad_package_names_the_install_command(monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "rad.optim", None)
    with pytest.raises(ImportError, match="pip install pytorch-rad"):
        DACERF("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(optimizer_class="RAD"))


def test_unknown_optimizer_name():
    with pytest.raises(ValueError, match="Unknown optimizer 'Adamm'"):
        DACERF("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(optimizer_class="Adamm"))


def test_multi_discrete_actions_are_refused():
    env = SimpleMultiObsEnv(discrete_actions=True)
    with pytest.raises(TypeError, match="needs a continuous action space"):
        DACERF("MultiInputPolicy", env)


class UnboundedActions(gym.Env):
    observation_space = spaces.Box(-1, 1, (2,), np.float32)
    action_space = spaces.Box(-np.inf, np.inf, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


def test_unbounded_actions_are_refused():
    with pytest.raises(ValueError, match="bounded action space"):
        DACERF("MlpPolicy", UnboundedActions())


@pytest.mark.parametrize(
    "name, value",
    [
        ("langevin_steps", -1),
        ("langevin_steps", 2.5),
        ("langevin_step_size", 0.0),
        ("langevin_temperature", -0.01),
        ("langevin_temperature", float("inf")),
        ("langevin_step_size", float("nan")),
        ("flow_matching_coef", float("inf")),
        ("flow_matching_coef", -1.0),
        ("n_steps", 0),
        ("n_steps", 2.5),
    ],
)
def test_invalid_hyperparameters(name, value):
    with pytest.raises(ValueError, match=f"Invalid {name}="):
        DACERF("MlpPolicy", "Pendulum-v1", **{name: value})


def test_invalid_policy_arguments():
    with pytest.raises(ValueError, match="Invalid n_sampling_steps=0"):
        DACERF("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(n_sampling_steps=0))
    with pytest.raises(ValueError, match="Invalid critic='layernorm': it must be one of 'mlp', 'layer_norm', 'batch_renorm'"):
        DACERF("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(critic="layernorm"))


def test_langevin_targets_method_follows_the_model_settings_and_leaves_the_critic_untouched(fast):
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, langevin_steps=5, **fast)
    model.learn(120)
    batch = model.replay_buffer.sample(64)
    observations, actions = batch.observations, batch.actions
    model.critic.optimizer.zero_grad(set_to_none=True)
    th.manual_seed(1)
    targets = model.langevin_targets(observations, actions)
    th.manual_seed(1)
    expected = langevin_targets(
        MinQActionGradient(model.critic, observations),
        actions,
        n_steps=5,
        step_size=model.langevin_step_size,
        temperature=model.langevin_temperature,
    )
    assert th.equal(targets, expected) and not targets.requires_grad
    assert all(param.grad is None for param in model.critic.parameters())
    assert all(param.requires_grad for param in model.critic.parameters())


class NanRewardPendulum(gym.Wrapper):
    def step(self, action):
        observation, _, terminated, truncated, info = self.env.step(action)
        return observation, float("nan"), terminated, truncated, info


def test_non_finite_rewards_stop_training_with_the_cause_and_keep_the_model(fast):
    model = DACERF("MlpPolicy", NanRewardPendulum(gym.make("Pendulum-v1")), seed=0, **fast)
    parameters = [p.clone() for p in model.policy.parameters()]
    # a ValueError too, so that RL Zoo's -optimize prunes the trial instead of stopping the study
    with pytest.raises(ValueError, match=r"non-finite critic loss.*non-finite rewards.*VecCheckNan") as error:
        model.learn(100)
    assert isinstance(error.value, RuntimeError)
    assert all(th.equal(a, b) for a, b in zip(parameters, model.policy.parameters(), strict=True))
    model.predict(model.observation_space.sample(), deterministic=True)


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_training_and_prediction(tmp_path, fast):
    model = DACERF("MlpPolicy", "Pendulum-v1", device="cuda", seed=0, **fast)
    model.learn(120)
    assert all(p.device.type == "cuda" for p in model.policy.parameters())
    model.save(tmp_path / "cuda")
    cpu_model = DACERF.load(tmp_path / "cuda", device="cpu")
    observation = model.observation_space.sample()
    np.testing.assert_allclose(
        cpu_model.predict(observation, deterministic=True)[0], model.predict(observation, deterministic=True)[0], atol=1e-5
    )


def distributional_model(fast) -> DACERF:
    """A DACERF with Gaussian critics and a filled replay buffer, before its first update."""
    fast["policy_kwargs"]["distributional_critic"] = True
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, **{**fast, "learning_starts": 1_000})
    with pytest.warns(UserWarning, match="without a single gradient step"):
        model.learn(60)
    return model


def test_distributional_critic_loss_is_dsac_t_without_the_entropy_term(fast):
    """The first update's critic loss of Gaussian critics against DSAC-T's written out here (targets from the smaller
    target mean and its sample, no entropy term; ω̄ the batch's mean σ), and its gradients."""
    model = distributional_model(fast)
    assert model.replay_buffer is not None
    batch = model.replay_buffer.sample(32)
    with th.no_grad():
        next_actions = model.actor(batch.next_observations)
    th.manual_seed(7)
    loss = model._distributional_critic_loss(batch, next_actions)
    th.manual_seed(7)

    def gaussian(critic, obs, actions):
        outputs = critic.ensemble(th.cat([critic.extract_features(obs, critic.features_extractor), actions], dim=1))
        return [(output[:, :1], th.nn.functional.softplus(output[:, 1:])) for output in outputs]

    with th.no_grad():
        (m1, s1), (m2, s2) = gaussian(model.critic_target, batch.next_observations, next_actions)
        z1, z2 = th.randn_like(m1).clamp(-3, 3), th.randn_like(m2).clamp(-3, 3)
        target = batch.rewards + (1 - batch.dones) * 0.99 * th.min(m1, m2)
        target_sample = batch.rewards + (1 - batch.dones) * 0.99 * th.where(m1 < m2, m1 + z1 * s1, m2 + z2 * s2)
    expected = th.zeros(())
    for q, q_std in gaussian(model.critic, batch.observations, batch.actions):
        mean_std, std_d = q_std.detach().mean(), q_std.detach()
        bound = q.detach() + th.clamp(target_sample - q.detach(), -3 * mean_std, 3 * mean_std)
        ratio = (mean_std**2 / (std_d**2 + 0.1)).clamp(0.1, 10)
        huber_q = th.nn.functional.huber_loss(q, target, delta=50, reduction="none")
        huber_bound = th.nn.functional.huber_loss(q.detach(), bound, delta=50, reduction="none")
        expected = expected + th.mean(ratio * (huber_q + q_std * (std_d**2 - huber_bound) / (std_d + 0.1)))
    th.testing.assert_close(loss, expected)
    parameters = list(model.critic.parameters())
    for got, want in zip(th.autograd.grad(loss, parameters), th.autograd.grad(expected, parameters), strict=True):
        th.testing.assert_close(got, want)
    batch_stds = [std.mean().item() for _, std in gaussian(model.critic, batch.observations, batch.actions)]
    assert model.running_std == pytest.approx(batch_stds)


def test_langevin_gradient_of_a_distributional_critic_is_that_of_its_mean(fast):
    model = distributional_model(fast)
    observations, actions = th.randn((16, 3)), th.rand((16, 1)) * 2 - 1
    with th.enable_grad():
        actions_grad = actions.clone().requires_grad_(True)
        min_q = model.critic.q_values(observations, actions_grad).min(dim=0).values
        (expected,) = th.autograd.grad(min_q.sum(), actions_grad)
    th.testing.assert_close(MinQActionGradient(model.critic, observations)(actions), expected)
    assert model.critic.q_values(observations, actions).shape == (2, 16, 1)


def test_distributional_critic_learns_logs_saves_and_loads(tmp_path, fast):
    fast["policy_kwargs"]["distributional_critic"] = True
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    with open(tmp_path / "progress.csv") as file:
        last = list(csv.DictReader(file))[-1]
    assert float(last["train/running_std1"]) > 0 and float(last["train/running_std2"]) > 0
    model.save(tmp_path / "model")
    loaded = DACERF.load(tmp_path / "model")
    assert loaded.critic.distributional and loaded.critic_target.distributional
    assert loaded.running_std == model.running_std
    assert loaded.policy_kwargs["distributional_critic"] is True
    observation = np.zeros(3, dtype=np.float32)
    np.testing.assert_allclose(
        loaded.predict(observation, deterministic=True)[0], model.predict(observation, deterministic=True)[0]
    )


@pytest.mark.parametrize(
    "policy_kwargs, message",
    [(dict(critic="batch_renorm"), "not critic='batch_renorm'"), (dict(n_critics=3), "n_critics=3 must be 2")],
)
def test_distributional_critic_refuses_what_its_targets_cannot_take(policy_kwargs, message):
    with pytest.raises(ValueError, match=message):
        DACERF("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(distributional_critic=True, **policy_kwargs))
