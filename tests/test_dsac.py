"""
DSAC (DSAC-T): its formulas against hand-computed values, the authors' defaults and where this class departs from
them, the order and timing of its updates, its options and its errors. The SB3 interface it shares with the other
algorithms is tested in test_algorithms.py.
"""

import copy
import inspect
import math
from pathlib import Path

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

from sb3_dacerf import DACERF, DSAC
from sb3_dacerf.dsac import dsac as dsac_module
from sb3_dacerf.dsac.dsac import bounded_target, critic_loss, distributional_targets
from sb3_dacerf.dsac.policies import TANH_EPSILON, GaussianCritic

DOCS = Path(__file__).parent.parent / "docs" / "modules" / "dsac.md"
#: The authors' code these defaults were checked against
DSAC_V2_COMMIT = "53447f45cee394a01c1fac2a8b2cd6db1a1f6d54"  # Jingliang-Duan/DSAC-v2: dsac_v2.py, networks/mlp.py, example_train/
GOPS_COMMIT = "74c3601de6f3fe0b06e44df5d7b9b8e14f800b98"  # Intelligent-Driving-Laboratory/GOPS: gops/algorithm/dsact.py

#: Where DSAC departs from the authors' code (DSAC-v2 at DSAC_V2_COMMIT): argument -> (our default, the authors'
#: setting). Each is listed on the documentation page with the commit.
DEPARTURES = {
    # SB3's default; the authors fill the buffer with 10,000 transitions first (buffer_warm_size, example_train/*.py)
    "learning_starts": (100, 10_000),
    # SB3's one environment step per gradient step; the authors' sampler adds 20 transitions per update
    # (sample_batch_size=20, sample_interval=1 in example_train/*.py): train_freq=20 reproduces that ratio
    "train_freq": (1, 20),
}


@pytest.fixture
def model_class() -> type:
    return DSAC


def test_official_defaults():
    model = DSAC("MlpPolicy", "Pendulum-v1", buffer_size=1)
    # dsac_v2.py and example_train/main.py, dsacv2_mlp_mujoco_offserial.py
    assert model.learning_rate == 1e-4  # value_learning_rate = policy_learning_rate = 1e-4
    assert model.actor.optimizer.param_groups[0]["lr"] == model.critic.optimizer.param_groups[0]["lr"] == 1e-4
    assert model.alpha_learning_rate == 3e-4  # alpha_learning_rate
    assert (model.gamma, model.tau, model.batch_size, model.policy_delay) == (0.99, 0.005, 256, 2)  # delay_update 2
    assert model.tau_b == model.tau  # tau_b = kwargs.get("tau_b", self.tau)
    assert inspect.signature(DSAC).parameters["buffer_size"].default == 1_000_000  # buffer_max_size 2 * 500000
    assert model.log_ent_coef.item() == pytest.approx(1.0)  # log_alpha = nn.Parameter(torch.tensor(1))
    assert model.ent_coef_optimizer is not None  # auto_alpha True
    assert model.ent_coef_optimizer.param_groups[0]["lr"] == 3e-4
    assert model.target_entropy == -1.0  # -action_dim
    # networks/mlp.py: 3 x 256 GELU, the policy's mean and log σ from one network (std_type "mlp_shared"), log σ in
    # [-20, 0.5]; the critic outputs a mean and softplus(σ)
    linear = [m.out_features for m in model.actor.network if isinstance(m, th.nn.Linear)]
    assert linear == [256, 256, 256, 2]
    assert all(isinstance(m, th.nn.GELU) for m in model.actor.network if not isinstance(m, th.nn.Linear))
    assert (model.actor.log_std_min, model.actor.log_std_max) == (-20.0, 0.5)
    assert isinstance(model.critic, GaussianCritic) and len(model.critic.q_networks) == 2
    for q_net in model.critic.q_networks:
        assert [m.out_features for m in q_net if isinstance(m, th.nn.Linear)] == [256, 256, 256, 2]
        assert any(isinstance(m, th.nn.GELU) for m in q_net)
    # The constants of the critic update (dsac_v2.py): bias 0.1, ratio clamp [0.1, 10], Huber delta 50,
    # td_bound = 3 * mean_std, z clamped to [-3, 3]; act_distribution_cls.py: EPS = 1e-6
    assert dsac_module.STD_EPSILON == 0.1
    assert dsac_module.WEIGHT_RANGE == (0.1, 10.0)
    assert dsac_module.HUBER_DELTA == 50.0
    assert dsac_module.TARGET_BOUND_SCALE == 3.0
    assert dsac_module.SAMPLE_CLIP == 3.0
    assert TANH_EPSILON == 1e-6
    # The departures: our defaults, and the documentation page names each with the authors' value and commit
    text = DOCS.read_text()
    assert DSAC_V2_COMMIT in text and GOPS_COMMIT in text
    ours = {"learning_starts": model.learning_starts, "train_freq": model.train_freq.frequency}
    for name, (default, theirs) in DEPARTURES.items():
        assert ours[name] == default, name
        assert f"`{name}`" in text and f"{theirs:,}" in text, name


def test_distributional_targets_hand_computed():
    rewards = th.tensor([[1.0], [2.0], [0.5]])
    discounts = th.tensor([[0.9], [0.9], [0.0]])  # the third transition is terminal
    mean_1, std_1 = th.tensor([[10.0], [4.0], [7.0]]), th.tensor([[2.0], [1.0], [1.0]])
    mean_2, std_2 = th.tensor([[12.0], [3.0], [9.0]]), th.tensor([[5.0], [0.5], [1.0]])
    normals = [th.tensor([[0.5], [1.0], [1.0]]), th.tensor([[2.0], [-4.0], [1.0]])]  # -4 is clipped to -3
    log_prob = th.tensor([[-1.0], [2.0], [0.0]])
    target_mean, target_sample = distributional_targets(
        rewards, discounts, ((mean_1, std_1), (mean_2, std_2)), log_prob, 0.5, normals
    )
    # Row 1: critic 1 has the smaller mean (10): y = 1 + 0.9 (10 + 0.5) = 10.45, y_z = 1 + 0.9 (10 + 0.5·2 + 0.5) = 11.35
    # Row 2: critic 2 (3): y = 2 + 0.9 (3 - 1) = 3.8, y_z = 2 + 0.9 (3 - 3·0.5 - 1) = 2.45
    # Row 3: terminal: y = y_z = r = 0.5
    th.testing.assert_close(target_mean, th.tensor([[10.45], [3.8], [0.5]]))
    th.testing.assert_close(target_sample, th.tensor([[11.35], [2.45], [0.5]]))


def test_bounded_target_hand_computed():
    current = th.tensor([[1.0], [1.0], [1.0], [-2.0]], requires_grad=True)
    sampled = th.tensor([[2.0], [10.0], [-10.0], [-3.5]])
    # ω̄ = 0.5: the sample may move at most 3 · 0.5 = 1.5 away from Q
    bounded = bounded_target(current, sampled, 0.5)
    th.testing.assert_close(bounded, th.tensor([[2.0], [2.5], [-0.5], [-3.5]]))
    assert not bounded.requires_grad


def _gradients(mean, std, target_mean, target_bound, running_std):
    mean = th.tensor(mean, requires_grad=True)
    std = th.tensor(std, requires_grad=True)
    critic_loss(mean, std, th.tensor(target_mean), th.tensor(target_bound), running_std).backward()
    assert mean.grad is not None and std.grad is not None
    return mean.grad, std.grad


def test_dsac_v2_critic_loss_gradients_hand_computed():
    # Batch of 3, ω̄ = 1: weights clip(1 / (σ² + 0.1), 0.1, 10) = 1 / 1.1, 1 / 0.14 and 0.1 (σ = 4: 1 / 16.1 is below)
    mean = [[2.0], [0.0], [100.0]]
    std = [[1.0], [0.2], [4.0]]
    target_mean = [[1.0], [1.0], [0.0]]  # the third is 100 away: Huber's linear part, gradient ±δ = 50
    target_bound = [[3.0], [0.0], [97.0]]
    mean_grad, std_grad = _gradients(mean, std, target_mean, target_bound, 1.0)
    w = [1 / 1.1, 1 / 0.14, 0.1]
    # ∂/∂Q = w (Q - y) (|Q - y| <= 50), w δ sign(Q - y) beyond; divided by the batch size 3
    expected_mean = [w[0] * 1.0 / 3, w[1] * -1.0 / 3, w[2] * 50.0 / 3]
    # ∂/∂σ = w (σ² - huber(Q - y_b)) / (σ + 0.1), huber(x) = x² / 2 (all |x| <= 50 here)
    expected_std = [
        w[0] * (1.0 - 0.5 * 1.0) / 1.1 / 3,
        w[1] * (0.04 - 0.0) / 0.3 / 3,
        w[2] * (16.0 - 0.5 * 9.0) / 4.1 / 3,
    ]
    th.testing.assert_close(mean_grad, th.tensor(expected_mean).reshape(3, 1))
    th.testing.assert_close(std_grad, th.tensor(expected_std).reshape(3, 1))
    # The weight is clipped at 10 for small σ: σ = 0.01, ω̄ = 2 gives 4 / 0.1001 = 40 -> 10
    mean_grad, _ = _gradients([[0.0]], [[0.01]], [[1.0]], [[0.0]], 2.0)
    th.testing.assert_close(mean_grad, th.tensor([[-10.0]]))


def test_critic_outputs_positive_standard_deviations_and_means_as_q_values(fast):
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    obs = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(64)]))
    actions = th.rand(64, 1) * 2 - 1
    with th.no_grad():
        distributions = model.critic.distributions(obs, actions)
        means = model.critic(obs, actions)
    assert len(distributions) == 2
    for (mean, std), q_value in zip(distributions, means, strict=True):
        assert mean.shape == std.shape == (64, 1) and bool((std > 0).all())
        assert th.equal(mean, q_value)


def test_log_prob_is_that_of_the_tanh_gaussian(fast):
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    obs = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(8)]))
    features = model.actor.extract_features(obs, model.actor.features_extractor)
    th.manual_seed(1)
    actions, log_prob = model.actor.sample_with_log_prob(features)
    th.manual_seed(1)
    mean, log_std = model.actor.distribution_parameters(features)
    gaussian = mean + log_std.exp() * th.randn_like(mean)
    expected = (
        -0.5 * ((gaussian - mean) / log_std.exp()) ** 2
        - log_std
        - 0.5 * math.log(2 * math.pi)
        - th.log(1 - th.tanh(gaussian) ** 2 + 1e-6)
    ).sum(dim=1)
    th.testing.assert_close(actions, th.tanh(gaussian))
    th.testing.assert_close(log_prob, expected)


def _fill_buffer(model: DSAC) -> None:
    """60 environment steps into the replay buffer, no update (``learning_starts`` is above)."""
    with pytest.warns(UserWarning, match="without a single gradient step"):
        model.learn(60)


def _record_batches(model: DSAC) -> list[list[float]]:
    """Wrap the replay buffer's ``sample`` to record the critics' mean σ on each batch, before the update."""
    recorded: list[list[float]] = []
    buffer = model.replay_buffer
    assert buffer is not None
    original = buffer.sample

    def sample(*args, **kwargs):
        batch = original(*args, **kwargs)
        with th.no_grad():
            recorded.append([std.mean().item() for _, std in model.critic.distributions(batch.observations, batch.actions)])
        return batch

    buffer.sample = sample  # type: ignore[method-assign]
    return recorded


def test_one_update_is_dsac_t_written_out(fast):
    """
    One update (the first: critics, actor, α and targets) against DSAC-T written out here from the authors'
    ``dsac_v2.py``, with the same random draws: every parameter and ``log α`` must come out the same.
    """
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, **{**fast, "learning_starts": 1_000})
    _fill_buffer(model)
    assert model.replay_buffer is not None
    batch = model.replay_buffer.sample(32)
    reference = copy.deepcopy(model)

    model._n_updates = 1
    th.manual_seed(7)
    model._update(batch)

    th.manual_seed(7)
    obs, actions, rewards, next_obs, dones = (
        batch.observations,
        batch.actions,
        batch.rewards,
        batch.next_observations,
        batch.dones,
    )
    alpha = reference.log_ent_coef.exp().item()
    with th.no_grad():
        next_actions, next_log_prob = reference.actor_target.action_log_prob(next_obs)  # the target policy
        (m1, s1), (m2, s2) = reference.critic_target.distributions(next_obs, next_actions)
        z1, z2 = th.randn_like(m1).clamp(-3, 3), th.randn_like(m2).clamp(-3, 3)
        q_next = th.min(m1, m2)
        q_next_sample = th.where(m1 < m2, m1 + z1 * s1, m2 + z2 * s2)
        target_q = rewards + (1 - dones) * 0.99 * (q_next - alpha * next_log_prob[:, None])
        target_q_sample = rewards + (1 - dones) * 0.99 * (q_next_sample - alpha * next_log_prob[:, None])
    critic_loss_value = th.zeros(())
    for q, q_std in reference.critic.distributions(obs, actions):
        mean_std = q_std.detach().mean()  # the first update: the running mean starts at the batch's
        bound = q.detach() + th.clamp(target_q_sample - q.detach(), -3 * mean_std, 3 * mean_std)
        std_d = q_std.detach()
        ratio = (mean_std**2 / (std_d**2 + 0.1)).clamp(0.1, 10)
        huber_q = th.nn.functional.huber_loss(q, target_q, delta=50, reduction="none")
        huber_bound = th.nn.functional.huber_loss(q.detach(), bound, delta=50, reduction="none")
        critic_loss_value = critic_loss_value + th.mean(ratio * (huber_q + q_std * (std_d**2 - huber_bound) / (std_d + 0.1)))
    critic_parameters = list(reference.critic.parameters())
    critic_gradients = th.autograd.grad(critic_loss_value, critic_parameters)
    # The actor's loss with the critics of before their step
    new_actions, log_prob = reference.actor.action_log_prob(obs)
    q_pi = th.min(*reference.critic(obs, new_actions))
    actor_loss = (alpha * log_prob[:, None] - q_pi).mean()
    actor_parameters = list(reference.actor.parameters())
    actor_gradients = th.autograd.grad(actor_loss, actor_parameters)
    for parameter, gradient in zip(critic_parameters, critic_gradients, strict=True):
        parameter.grad = gradient
    for parameter, gradient in zip(actor_parameters, actor_gradients, strict=True):
        parameter.grad = gradient
    reference.critic.optimizer.step()
    reference.actor.optimizer.step()
    # loss_alpha = -log_alpha * (log_prob + target_entropy).mean()
    assert reference.ent_coef_optimizer is not None
    reference.log_ent_coef.grad = -(log_prob.detach().mean() + reference.target_entropy).reshape(())
    reference.ent_coef_optimizer.step()
    with th.no_grad():
        for online, target in [(reference.critic, reference.critic_target), (reference.actor, reference.actor_target)]:
            for p, p_target in zip(online.parameters(), target.parameters(), strict=True):
                p_target.mul_(1 - 0.005).add_(0.005 * p)

    for (name, ours), theirs in zip(model.policy.state_dict().items(), reference.policy.state_dict().values(), strict=True):
        th.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-6, msg=name)


def test_running_std_starts_at_the_first_batch_and_is_smoothed_by_tau_b(fast):
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, tau_b=0.25, **{**fast, "learning_starts": 1_000})
    _fill_buffer(model)
    assert model.running_std is None
    recorded = _record_batches(model)
    model.train(gradient_steps=1, batch_size=32)
    assert model.running_std == pytest.approx(recorded[0], rel=1e-6)
    model.train(gradient_steps=1, batch_size=32)
    expected = [0.75 * old + 0.25 * new for old, new in zip(recorded[0], recorded[1], strict=True)]
    assert model.running_std == pytest.approx(expected, rel=1e-6)


def test_actor_alpha_and_targets_update_at_the_first_update_then_every_policy_delay(fast):
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, policy_delay=3, **{**fast, "learning_starts": 1_000})
    _fill_buffer(model)

    def snapshot():
        return (
            [p.clone() for p in model.actor.parameters()],
            model.log_ent_coef.clone(),
            [p.clone() for p in model.actor_target.parameters()],
            [p.clone() for p in model.critic_target.parameters()],
            [p.clone() for p in model.critic.parameters()],
        )

    def changed(before, after):
        return [
            not all(th.equal(a, b) for a, b in zip(x, y, strict=True)) if isinstance(x, list) else not th.equal(x, y)
            for x, y in zip(before, after, strict=True)
        ]

    pattern = []
    for _ in range(5):  # updates 1..5: the actor side moves at 1 and 4
        before = snapshot()
        model.train(gradient_steps=1, batch_size=32)
        pattern.append(changed(before, snapshot()))
    assert pattern == [[True] * 5, [False] * 4 + [True], [False] * 4 + [True], [True] * 5, [False] * 4 + [True]]


def test_target_policy_gives_the_next_actions_and_the_actor_trains_on_its_own_samples(fast):
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, policy_delay=2, **{**fast, "learning_starts": 1_000})
    _fill_buffer(model)
    calls = {"actor": 0, "actor_target": 0}
    model.actor.network.register_forward_hook(lambda *_: calls.__setitem__("actor", calls["actor"] + 1))
    model.actor_target.network.register_forward_hook(lambda *_: calls.__setitem__("actor_target", calls["actor_target"] + 1))
    model.train(gradient_steps=4, batch_size=32)
    assert calls == {"actor_target": 4, "actor": 2}


@pytest.mark.parametrize("target_entropy, direction", [(-100.0, -1), (100.0, 1)])
def test_alpha_moves_towards_the_target_entropy(target_entropy, direction, fast):
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, target_entropy=target_entropy, **fast)
    model.learn(100)
    assert np.sign(model.log_ent_coef.item() - 1.0) == direction


@pytest.mark.parametrize("ent_coef, log_alpha", [(0.2, math.log(0.2)), (0.0, -math.inf), ("auto_0.5", math.log(0.5))])
def test_ent_coef_fixed_or_learned_from_a_given_start(ent_coef, log_alpha, fast):
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, ent_coef=ent_coef, **fast)
    assert model.log_ent_coef.item() == pytest.approx(log_alpha)
    model.learn(80)
    if isinstance(ent_coef, str):
        assert model.ent_coef_optimizer is not None and model.log_ent_coef.item() != pytest.approx(log_alpha)
    else:
        assert model.ent_coef_optimizer is None and model.log_ent_coef.item() == pytest.approx(log_alpha)


def test_layer_norm_critics(fast):
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, policy_kwargs=dict(net_arch=[32, 32], critic="layer_norm"))
    assert any(isinstance(m, th.nn.LayerNorm) for m in model.critic.q_networks[0])


def test_logs_both_critics_mean_and_std_alpha_and_entropy(tmp_path, fast):
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    header = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    for key in (
        "q1_mean",
        "q2_mean",
        "q1_std",
        "q2_std",
        "running_std1",
        "running_std2",
        "ent_coef",
        "ent_coef_loss",
        "entropy",
        "actor_loss",
        "critic_loss",
    ):
        assert f"train/{key}" in header, key


def test_learns_on_a_vec_env_of_several_environments(fast):
    env = make_vec_env("Pendulum-v1", n_envs=2, seed=0)
    model = DSAC("MlpPolicy", env, seed=0, **fast)
    model.learn(120)
    assert model.num_timesteps == 120 and model._n_updates == 35  # one gradient step per rollout of 2 transitions
    assert model.predict(env.reset(), deterministic=True)[0].shape == (2, 1)


def test_callbacks_and_tensorboard_keys(tmp_path, fast):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, tensorboard_log=str(tmp_path / "tb"), **fast)
    model.learn(100, callback=CheckpointCallback(save_freq=50, save_path=str(tmp_path / "ckpt")))
    assert len(list((tmp_path / "ckpt").glob("*.zip"))) == 2
    events = EventAccumulator(str(tmp_path / "tb" / "DSAC_1"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    critics = {f"train/q{i}_{what}" for i in (1, 2) for what in ("mean", "std")} | {"train/running_std1", "train/running_std2"}
    assert critics | {"train/ent_coef", "train/entropy", "train/actor_loss", "train/critic_loss"} <= tags


def test_another_algorithms_file_is_refused_with_its_name(tmp_path, fast):
    DSAC("MlpPolicy", "Pendulum-v1", **fast).save(tmp_path / "dsac")
    with pytest.raises(ValueError, match=r"holds a DSAC model .*load it with DSAC\.load"):
        DACERF.load(tmp_path / "dsac.zip")
    DACERF("MlpPolicy", "Pendulum-v1", buffer_size=1).save(tmp_path / "dacerf")
    with pytest.raises(ValueError, match=r"holds a DACERF model .*load it with DACERF\.load"):
        DSAC.load(tmp_path / "dacerf.zip")


def test_save_load_keeps_the_running_std_alpha_and_optimizers(tmp_path, fast):
    model = DSAC("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    model.learn(100)
    model.save(tmp_path / "model")
    loaded = DSAC.load(tmp_path / "model")
    assert loaded.running_std == model.running_std
    assert loaded.log_ent_coef.item() == model.log_ent_coef.item()
    assert loaded.ent_coef_optimizer is not None and model.ent_coef_optimizer is not None
    assert loaded.ent_coef_optimizer.state_dict()["state"][0]["step"] == model.ent_coef_optimizer.state_dict()["state"][0]["step"]
    for a, b in zip(loaded.actor_target.parameters(), model.actor_target.parameters(), strict=True):
        assert th.equal(a, b)
    loaded.set_env(model.get_env())
    loaded.learn(20, reset_num_timesteps=False)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(ent_coef="automatic"), "Invalid ent_coef='automatic'"),
        (dict(ent_coef="auto_-1"), "Invalid ent_coef='auto_-1'"),
        (dict(ent_coef=-0.1), "Invalid ent_coef=-0.1"),
        (dict(ent_coef=True), "Invalid ent_coef=True"),
        (dict(tau_b=0.0), r"Invalid tau_b=0.0: it must be in \(0, 1\]"),
        (dict(tau_b=1.5), "Invalid tau_b=1.5"),
        (dict(alpha_learning_rate=0), "Invalid alpha_learning_rate=0"),
        (dict(policy_kwargs=dict(n_critics=3)), "exactly two critics.*n_critics=3"),
        (dict(policy_kwargs=dict(critic="batch_renorm")), "critic='batch_renorm'.*critic='layer_norm'"),
        (dict(policy_kwargs=dict(log_std_min=1.0, log_std_max=0.5)), "log_std_min < log_std_max"),
        (dict(policy_kwargs=dict(exploration_noise_scale=0.1)), "unexpected keyword|exploration_noise_scale"),
    ],
)
def test_bad_input_is_refused_with_the_valid_values(kwargs, message):
    with pytest.raises((ValueError, TypeError), match=message):
        DSAC("MlpPolicy", "Pendulum-v1", buffer_size=1, **kwargs)
