"""
What the algorithms share (DACER, DACERF, DSAC), tested on each (``model_class``, see conftest.py): the SB3 algorithm interface
(constructor, learn, predict, save and load, observation spaces), the generative actor interface, and the
hyper-parameter checks.
"""

import copy
import inspect
import math

import numpy as np
import pytest
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import FakeImageEnv, SimpleMultiObsEnv
from stable_baselines3.common.logger import configure
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

from sb3_dacerf import DACER, DACERF, DSAC
from sb3_dacerf.common.policies import GenerativeActor
from sb3_dacerf.common.twin_critic import TwinCriticAlgorithm

# SAC's own options, which a generative policy has no use for
SAC_ONLY = {"ent_coef", "target_update_interval", "use_sde", "sde_sample_freq", "use_sde_at_warmup"}
# Arguments with the same meaning and default value as SAC's (the plumbing of SB3's OffPolicyAlgorithm)
SB3_ARGUMENTS = [
    "buffer_size",
    "train_freq",
    "gradient_steps",
    "action_noise",
    "replay_buffer_class",
    "replay_buffer_kwargs",
    "optimize_memory_usage",
    "n_steps",
    "stats_window_size",
    "tensorboard_log",
    "policy_kwargs",
    "verbose",
    "seed",
    "device",
    "_init_setup_model",
]


def observations(model, n: int = 16) -> np.ndarray:
    return np.stack([model.observation_space.sample() for _ in range(n)])


def test_constructor_arguments_are_explicit(model_class):
    parameters = dict(inspect.signature(model_class).parameters)
    kinds = {parameter.kind for parameter in parameters.values()}
    assert inspect.Parameter.VAR_KEYWORD not in kinds and inspect.Parameter.VAR_POSITIONAL not in kinds
    with pytest.raises(
        TypeError, match=f"{model_class.__name__}.__init__\\(\\) got an unexpected keyword argument 'learning_rte'"
    ):
        model_class("MlpPolicy", "Pendulum-v1", learning_rte=1e-3)
    sac = inspect.signature(SAC).parameters
    assert set(sac) - SAC_ONLY <= set(parameters)
    for name in SB3_ARGUMENTS:
        assert parameters[name].default == sac[name].default, name
    # The algorithm's own arguments are kept (and saved): as attributes, or in policy_kwargs for those of the policy
    model = model_class("MlpPolicy", "Pendulum-v1", buffer_size=1)
    for name in set(parameters) - set(inspect.signature(OffPolicyAlgorithm).parameters) - {"_init_setup_model"}:
        assert hasattr(model, name) or name in model.policy_kwargs, name


def test_hyperparameter_rules_belong_to_their_algorithm(model_class):
    rules = model_class.hyperparameter_rules
    assert set(TwinCriticAlgorithm.hyperparameter_rules) <= set(rules)
    # ... named as the algorithm's arguments, or as its policy's (n_sampling_steps, n_diffusion_steps)
    policy_parameters = inspect.signature(model_class.policy_aliases["MlpPolicy"]).parameters
    assert set(rules) <= set(inspect.signature(model_class).parameters) | set(policy_parameters)
    # Each algorithm checks its own hyper-parameters only; those of all of them are the base class's
    shared = set(TwinCriticAlgorithm.hyperparameter_rules)
    assert "policy_delay" in shared
    assert (set(DACER.hyperparameter_rules) - shared) & (set(DACERF.hyperparameter_rules) - shared) == set()


def test_one_base_class_between_off_policy_algorithm_and_the_algorithms(model_class):
    """The algorithms derive from TwinCriticAlgorithm, which holds the checks; saving and loading come with it."""
    from sb3_dacerf.common import persistence

    mro = model_class.__mro__
    assert mro[1:4] == (TwinCriticAlgorithm, persistence.TwinCriticPersistence, OffPolicyAlgorithm)
    for method in ("predict", "_checked", "_sample_action", "learn"):
        assert next(cls for cls in mro if method in vars(cls)) is TwinCriticAlgorithm, method
    for method in ("save", "load", "set_parameters"):
        assert next(cls for cls in mro if method in vars(cls)) is persistence.TwinCriticPersistence, method


@pytest.mark.parametrize(
    "name, value",
    [
        ("tau", 0.0),
        ("tau", 1.5),
        ("gamma", 1.2),
        ("batch_size", 0),
        ("batch_size", 2.0),
        ("policy_delay", 0),
        ("policy_delay", float("nan")),
        ("target_entropy", "high"),
        ("target_entropy", float("inf")),
        ("ent_coef", "automatic"),
        ("ent_coef", "auto_"),
        ("ent_coef", "auto_-1"),
        ("ent_coef", "auto_0"),
        ("ent_coef", -0.1),
        ("ent_coef", float("inf")),
        ("ent_coef", True),
        ("ent_coef", None),
    ],
)
def test_invalid_shared_hyperparameters_name_their_valid_range(model_class, name, value):
    with pytest.raises(ValueError, match=f"Invalid {name}="):
        model_class("MlpPolicy", "Pendulum-v1", **{name: value})


@pytest.mark.parametrize("ent_coef, alpha, learned", [("auto_0.5", 0.5, True), (0.2, 0.2, False), (0, 0.0, False)])
def test_ent_coef_sets_the_initial_temperature(model_class, ent_coef, alpha, learned):
    model = model_class("MlpPolicy", "Pendulum-v1", ent_coef=ent_coef)
    assert log_alpha(model).exp().item() == pytest.approx(alpha)
    assert log_alpha(model).requires_grad == learned
    assert (model.ent_coef_optimizer is not None) == learned
    # "auto": learned, from each algorithm's own start (DACER-F and DACER: α = 3; DSAC: α = e)
    auto = model_class("MlpPolicy", "Pendulum-v1", ent_coef="auto")
    assert auto.ent_coef_optimizer is not None
    assert log_alpha(auto).exp().item() == pytest.approx(math.e if model_class is DSAC else 3.0)


def test_learns_and_logs(model_class, fast, tmp_path):
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    header = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    for key in ("critic_loss", "actor_loss", "n_updates"):
        assert f"train/{key}" in header
    assert model._n_updates == 150


def test_save_load_gives_identical_predictions(model_class, fast, tmp_path):
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    model.learn(100)
    obs = observations(model)
    actions, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], actions)
    assert not np.array_equal(model.predict(obs)[0], actions)

    model.save(tmp_path / "model")
    loaded = model_class.load(tmp_path / "model")
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], actions)
    assert log_alpha(loaded).item() == log_alpha(model).item()

    # The policy alone (sb3-contrib's test_save_load_policy), and the actor alone
    model.policy.save(tmp_path / "policy.pkl")
    policy = type(model.policy).load(tmp_path / "policy.pkl")
    np.testing.assert_array_equal(policy.predict(obs, deterministic=True)[0], actions)
    model.actor.save(tmp_path / "actor.pkl")
    actor = type(model.actor).load(tmp_path / "actor.pkl")
    np.testing.assert_array_equal(actor.predict(obs, deterministic=True)[0], model.actor.predict(obs, deterministic=True)[0])


def test_predict_shapes_and_bounds(model_class, fast):
    env = make_vec_env("MountainCarContinuous-v0", n_envs=2, seed=0)
    model = model_class("MlpPolicy", env, seed=0, **fast)
    observation = env.observation_space.sample()
    assert model.predict(observation)[0].shape == (1,)
    actions, _ = model.predict(np.stack([observation] * 7))
    assert actions.shape == (7, 1) and np.all(np.abs(actions) <= 1)
    assert model.predict(env.reset())[0].shape == (2, 1)


def test_image_and_dict_observations(model_class, fast):
    env = FakeImageEnv(action_dim=2, screen_height=40, screen_width=40, n_channels=1, discrete=False)
    model = model_class("CnnPolicy", env, seed=0, **{**fast, "learning_starts": 20, "batch_size": 8, "buffer_size": 200})
    model.learn(30)
    action, _ = model.predict(env.observation_space.sample(), deterministic=True)
    assert action.shape == env.action_space.shape and env.action_space.contains(action)

    env = SimpleMultiObsEnv(random_start=False, discrete_actions=False)
    model = model_class("MultiInputPolicy", env, seed=0, **fast)
    model.learn(60)
    assert model.predict(env.observation_space.sample(), deterministic=True)[0].shape == env.action_space.shape


def test_same_seed_same_training(model_class, fast):
    def train(seed: int) -> list[th.Tensor]:
        model = model_class("MlpPolicy", "Pendulum-v1", seed=seed, **fast)
        model.learn(100)
        return [p.detach().clone() for p in model.policy.parameters()]

    first, second, other = train(3), train(3), train(4)
    assert all(th.equal(a, b) for a, b in zip(first, second, strict=True))
    assert not all(th.equal(a, b) for a, b in zip(first, other, strict=True))


def test_discrete_actions_are_refused_with_advice(model_class):
    with pytest.raises(TypeError, match=f"{model_class.__name__} needs a continuous action space.*Discrete\\(2\\).*DQN"):
        model_class("MlpPolicy", "CartPole-v1")


def log_alpha(model) -> th.Tensor:
    """``log α``: a parameter of DACER-F's and DACER's actors (it scales their exploration noise), DSAC's own."""
    return model.log_ent_coef if isinstance(model, DSAC) else model.actor.log_alpha


@pytest.mark.parametrize("model_class", [DACER, DACERF])
def test_actor_interface(model_class, fast):
    """The contract of GenerativeActor: sample(features, noise), draw_noise, add_exploration_noise, act, forward."""
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    actor = model.actor
    assert isinstance(actor, GenerativeActor)
    obs = th.as_tensor(observations(model, 64))
    features = actor.extract_features(obs, actor.features_extractor)

    noise = actor.draw_noise(features)
    assert noise.shape == (64, *actor.noise_shape)
    assert th.equal(actor.sample(features, noise), actor.sample(features, noise))  # a function of the noise
    assert not th.equal(actor.sample(features, noise), actor.sample(features, actor.draw_noise(features)))
    assert th.equal(actor.sample(features), actor.sample(features, th.zeros_like(noise)))
    assert th.equal(actor(obs, deterministic=True), actor.sample(features))
    assert th.equal(actor.act(features, deterministic=True), actor.sample(features))

    # A stochastic action: the generator's sample, then the exploration noise
    th.manual_seed(5)
    stochastic = actor(obs)
    th.manual_seed(5)
    expected = actor.add_exploration_noise(actor.sample(features, actor.draw_noise(features)))
    assert th.equal(stochastic, expected)
    assert stochastic.abs().max() <= 1.0
    # ... N(0, exploration_std²), clipped
    clean = actor.sample(features, actor.draw_noise(features))
    state = th.get_rng_state()
    xi = th.randn_like(clean)
    th.set_rng_state(state)
    assert th.equal(actor.add_exploration_noise(clean), (clean + actor.exploration_std * xi).clamp(-1, 1))

    # No exploration noise (and no random draw) at α = 0
    quiet = copy.deepcopy(actor)
    with th.no_grad():
        quiet.log_alpha.fill_(-math.inf)
    state = th.get_rng_state()
    assert quiet.add_exploration_noise(clean) is clean
    assert th.equal(th.get_rng_state(), state)

    # The sample is differentiable with respect to the generator's network, through all its steps
    actor.sample(features, noise).sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.network.parameters())
