"""Ensemble critics: each layer of all the critics in one batched product, equal to separate critic networks."""

import functools
import io
import os
import zipfile
from collections import OrderedDict
from copy import deepcopy

import numpy as np
import pytest
import torch as th
from sb3_dacerf.common.langevin import autograd_action_gradient, langevin_targets
from stable_baselines3.common.envs import IdentityEnvBox
from stable_baselines3.common.vec_env import DummyVecEnv
from torch import nn
from torch.nn import functional as F

from sb3_dacerf import DACER, DACERF
from sb3_dacerf.common.policies import (
    EnsembleBatchRenorm,
    EnsembleCritic,
    EnsembleLayerNorm,
    EnsembleLinear,
    convert_separate_critics_optimizer,
)
from sb3_dacerf.common.twin_critic import frozen
from sb3_dacerf.dacerf.dacerf import actor_loss_weights, flow_matching_loss

DATA = os.path.join(os.path.dirname(__file__), "data")
CRITICS = {
    "mlp": dict(critic="mlp"),
    "layer_norm": dict(critic="layer_norm"),
    "batch_renorm": dict(critic="batch_renorm"),
    "layer_norm_3_critics": dict(critic="layer_norm", n_critics=3),
}


def separate_networks(critic: EnsembleCritic) -> list[nn.Sequential]:
    """One network of plain layers per critic (nn.Linear, nn.LayerNorm, sb3-contrib's BatchRenorm1d) with the
    ensemble's weights: the critics as SB3's ContinuousCritic holds them."""
    networks = []
    for member in range(critic.n_critics):
        layers: list[nn.Module] = []
        for module in critic.ensemble:
            if isinstance(module, EnsembleLinear):
                layer: nn.Module = nn.Linear(module.in_features, module.out_features)
                layer.weight.data.copy_(module.weight[member].t())
                layer.bias.data.copy_(module.bias[member])
            elif isinstance(module, EnsembleLayerNorm):
                layer = nn.LayerNorm(module.num_features, eps=module.eps)
                layer.weight.data.copy_(module.weight[member])
                layer.bias.data.copy_(module.bias[member])
            elif isinstance(module, EnsembleBatchRenorm):
                from sb3_contrib.common.torch_layers import BatchRenorm1d

                layer = BatchRenorm1d(module.num_features, module.eps, module.momentum, warmup_steps=module.warmup_steps)
                for name in ("scale", "bias", "ra_mean", "ra_var"):
                    getattr(layer, name).data.copy_(getattr(module, name)[member])
                layer.steps.copy_(module.steps)
                layer.train(module.training)
            else:
                layer = module
            layers.append(layer)
        networks.append(nn.Sequential(*layers))
    return networks


def separate_q_values(critic: EnsembleCritic, networks: list[nn.Sequential], observations, actions) -> list[th.Tensor]:
    """``[Q_j(s, a)]`` as SB3's ContinuousCritic computes them: features once, then each network on (features, a)."""
    features = critic.extract_features(observations, critic.features_extractor)
    return [network(th.cat([features, actions], dim=1)) for network in networks]


def trained_model(critics: str, seed: int = 0) -> DACERF:
    kwargs = dict(CRITICS[critics])
    if kwargs.get("critic") == "batch_renorm":
        pytest.importorskip("sb3_contrib")
    model = DACERF(
        "MlpPolicy",
        "Pendulum-v1",
        learning_starts=50,
        batch_size=64,
        langevin_steps=5,
        policy_kwargs=dict(net_arch=[32, 32], **kwargs),
        seed=seed,
    )
    model.learn(100)  # away from the initial weights
    return model


def test_ensemble_linear_initialises_each_member_as_nn_linear():
    th.manual_seed(0)
    ensemble = EnsembleLinear(3, 5, 4)
    th.manual_seed(0)
    linears = [nn.Linear(5, 4) for _ in range(3)]
    for member, linear in enumerate(linears):
        assert th.equal(ensemble.weight[member], linear.weight.t()) and th.equal(ensemble.bias[member], linear.bias)
    x = th.randn(7, 5)
    assert th.allclose(ensemble(x), th.stack([linear(x) for linear in linears]), atol=1e-6)


@pytest.mark.parametrize("critics", list(CRITICS))
def test_critics_equal_separate_networks_with_the_same_weights(critics):
    """Fixed seed, one batch: the Bellman targets, the critic loss and its gradients, and the actor loss terms (Langevin
    targets included) are those of separate per-critic networks holding the same weights, to 1e-5."""
    model = trained_model(critics)
    batch = model.replay_buffer.sample(64)
    # Critic loss: the reference is the computation on separate networks (SB3's ContinuousCritic layout)
    networks = separate_networks(model.critic)
    target_networks = separate_networks(model.critic_target)
    th.manual_seed(11)
    terms = model.critic_terms(batch)
    th.manual_seed(11)
    with th.no_grad():
        next_actions = model.actor(batch.next_observations)
    if CRITICS[critics].get("critic") == "batch_renorm":  # one joint pass in training mode, no target networks
        for network in networks:
            network.train()
        joint = separate_q_values(
            model.critic,
            networks,
            th.cat([batch.observations, batch.next_observations]),
            th.cat([batch.actions, next_actions]),
        )
        current = [q_values[: len(batch.actions)] for q_values in joint]
        next_q_values = th.cat([q_values[len(batch.actions) :].detach() for q_values in joint], dim=1)
    else:
        with th.no_grad():
            next_q_values = th.cat(
                separate_q_values(model.critic_target, target_networks, batch.next_observations, next_actions), dim=1
            )
        current = separate_q_values(model.critic, networks, batch.observations, batch.actions)
    target = batch.rewards + (1 - batch.dones) * model.gamma * next_q_values.min(dim=1, keepdim=True).values
    loss = 0.5 * sum(F.mse_loss(q_values, target) for q_values in current)
    assert th.allclose(terms["target_q_values"], target, rtol=1e-5, atol=1e-5)
    assert th.allclose(terms["loss"], loss, rtol=1e-5, atol=1e-5)
    model.critic.optimizer.zero_grad()
    terms["loss"].backward()
    loss.backward()
    linears = [index for index, module in enumerate(model.critic.ensemble) if isinstance(module, EnsembleLinear)]
    for member, network in enumerate(networks):
        for index in linears:
            assert th.allclose(model.critic.ensemble[index].weight.grad[member], network[index].weight.grad.t(), atol=1e-5)
    if CRITICS[critics].get("critic") == "batch_renorm":  # and the pass moved the same running statistics
        for module, layer in zip(model.critic.ensemble, networks[0], strict=True):
            if isinstance(module, EnsembleBatchRenorm):
                assert th.allclose(module.ra_mean[0], layer.ra_mean, atol=1e-6) and module.steps == layer.steps
        for network in networks:
            network.eval()

    # Actor loss terms: Langevin targets by autograd through the separate networks, with the same random draws
    networks = separate_networks(model.critic)
    parameters = [param for network in networks for param in network.parameters()]
    features = model.critic.extract_features(batch.observations, model.critic.features_extractor)

    def min_q(actions):
        return (
            th.cat([network(th.cat([features, actions], dim=1)) for network in networks], dim=1).min(dim=1, keepdim=True).values
        )

    th.manual_seed(12)
    actor_terms = model.actor_loss_terms(batch)
    th.manual_seed(12)
    with frozen(parameters):
        targets = langevin_targets(
            autograd_action_gradient(min_q),
            batch.actions,
            model.langevin_steps,
            model.langevin_step_size,
            model.langevin_temperature,
        )
        with th.no_grad():
            q_star, q_buffer = min_q(targets), min_q(batch.actions)
        actor_features = model.actor.extract_features(batch.observations, model.actor.features_extractor)
        q_pi = min_q(model.actor.sample(actor_features, model.actor.draw_noise(actor_features)))
        kappa, lambda_f = actor_loss_weights(model.flow_matching_weights, q_pi, q_star, q_buffer, model.flow_matching_coef)
        flow_error = flow_matching_loss(functools.partial(model.actor.velocity, actor_features), targets)
    expected = dict(
        targets=targets,
        q_values_star=q_star,
        q_values_buffer=q_buffer,
        improvement_term=(-q_pi / kappa).mean(),
        imitation_term=(lambda_f * flow_error).mean(),
    )
    for name, value in expected.items():
        assert th.allclose(actor_terms[name], value, rtol=1e-5, atol=1e-5), name
    actor_parameters = list(model.actor.network.parameters())
    for got, want in zip(
        th.autograd.grad(actor_terms["improvement_term"], actor_parameters),
        th.autograd.grad(expected["improvement_term"], actor_parameters),
        strict=True,
    ):
        assert th.allclose(got, want, rtol=1e-5, atol=1e-5)


def separate_state_dict(critic: EnsembleCritic, prefix: str, names: tuple[str, ...]) -> dict[str, th.Tensor]:
    """The critic's entries as earlier versions saved them: ``<name><j>.<k>.*`` for each name of ``names``."""
    entries = {}
    for index, module in enumerate(critic.ensemble):
        for entry, value in [*module.named_parameters(), *module.named_buffers()]:
            for member in range(critic.n_critics):
                member_value = value if entry == "steps" else value[member]
                if isinstance(module, EnsembleLinear) and entry == "weight":
                    member_value = member_value.t()
                for name in names:
                    separator = "." if name == "q_networks" else ""
                    entries[f"{prefix}{name}{separator}{member}.{index}.{entry}"] = member_value.detach().clone()
    return entries


@pytest.mark.parametrize("critics", ["mlp", "layer_norm", "batch_renorm"])
def test_separate_critic_entries_and_their_optimizer_state_load_into_the_ensemble(critics):
    model = trained_model(critics)
    # the state dict and critic optimizer state of the same critics as separate networks (qf<j> and q_networks.<j>)
    policy_state = {key: value for key, value in model.policy.state_dict().items() if ".ensemble." not in key}
    for prefix in ("critic.", "critic_target."):
        policy_state.update(separate_state_dict(getattr(model, prefix[:-1]), prefix, ("qf", "q_networks")))
    current = model.critic.optimizer.state_dict()
    per_member = len(current["param_groups"][0]["params"])
    old_state = {}
    for position in range(per_member):
        for member in range(model.critic.n_critics):
            state = current["state"][position]
            old_state[member * per_member + position] = {
                key: (value[member].t() if value.dim() == 3 else value[member]) if value.dim() > 0 else value
                for key, value in state.items()
            }
    old_optimizer = {
        "state": old_state,
        "param_groups": [{**current["param_groups"][0], "params": list(range(model.critic.n_critics * per_member))}],
    }
    other = trained_model(critics, seed=1)
    other.set_parameters({"policy": policy_state, "critic.optimizer": old_optimizer}, exact_match=False)
    for key, value in model.policy.state_dict().items():
        assert th.equal(other.policy.state_dict()[key], value), key
    converted = other.critic.optimizer.state_dict()
    for position, state in current["state"].items():
        for key, value in state.items():
            assert th.equal(converted["state"][position][key], value), (position, key)
    with pytest.raises(ValueError, match="Cannot convert the saved critic optimizer"):
        convert_separate_critics_optimizer({"state": {}, "param_groups": [{"params": [0, 1, 2]}]}, model.critic, n_leading=0)


def zip_entries(path: str, name: str) -> dict:
    with zipfile.ZipFile(path) as archive:
        return th.load(io.BytesIO(archive.read(name)), weights_only=False)


@pytest.mark.parametrize("path", [os.path.join(DATA, "models_0.1.0", f"{name}.zip") for name in ("dacerf", "dacer")])
def test_models_saved_with_separate_critics_load_with_the_same_q_values(path):
    """sb3_dacerf 0.1.0's zips hold separate critic networks (SB3's MLP critics): loaded, the ensemble computes their
    Q-values, and the critic optimizer's state is theirs, stacked. Separate LayerNorm and batch-renorm critics are
    converted by test_separate_critic_entries_and_their_optimizer_state_load_into_the_ensemble."""
    model_class = DACER if os.path.basename(path) == "dacer.zip" else DACERF
    model = model_class.load(path, device="cpu")
    saved = zip_entries(path, "policy.pth")
    rng = np.random.default_rng(0)
    observations = th.as_tensor(rng.normal(size=(9, *model.observation_space.shape)), dtype=th.float32)
    actions = th.as_tensor(rng.uniform(-1, 1, size=(9, *model.action_space.shape)), dtype=th.float32)
    for prefix in ("critic", "critic_target"):
        critic = getattr(model, prefix)
        expected = []
        features = critic.extract_features(observations, critic.features_extractor)
        for member in range(critic.n_critics):
            x = th.cat([features, actions], dim=1)
            layers = sorted({int(key.split(".")[2]) for key in saved if key.startswith(f"{prefix}.qf{member}.")})
            for position, layer in enumerate(layers):
                x = F.linear(x, saved[f"{prefix}.qf{member}.{layer}.weight"], saved[f"{prefix}.qf{member}.{layer}.bias"])
                if position < len(layers) - 1:
                    x = critic.ensemble[layer + 1](x)  # the activation
            expected.append(x)
        with th.no_grad():
            assert th.allclose(critic.q_values(observations, actions), th.stack(expected), atol=1e-5), prefix
    saved_optimizer = zip_entries(path, "critic.optimizer.pth")
    state = model.critic.optimizer.state_dict()["state"]
    if saved_optimizer["state"]:
        per_member = len(state)
        for position, (name, _) in enumerate(model.critic.ensemble.named_parameters()):
            stacked = th.stack([saved_optimizer["state"][member * per_member + position]["exp_avg"] for member in range(2)])
            exp_avg = state[position]["exp_avg"]
            assert th.equal(exp_avg, stacked.transpose(1, 2) if name.endswith("weight") and stacked.dim() == 3 else stacked)


@pytest.mark.parametrize("model_class", [DACERF, DACER])
def test_get_and_set_parameters_follow_sb3s_save_load_contract(model_class, tmp_path):
    """The checks of SB3's own save/load test (stable-baselines3 2.9.2, tests/test_save_load.py::test_save_load):
    set_parameters refuses unknown objects and, with exact_match, missing ones; with exact_match=False it sets the
    tensors it is given and only those; save and load give the same parameters and actions."""
    env = DummyVecEnv([lambda: IdentityEnvBox(-10, 10)])
    policy_kwargs = dict(net_arch=[16], **(dict(n_diffusion_steps=3) if model_class is DACER else {}))
    model = model_class("MlpPolicy", env, learning_rate=1e-3, policy_kwargs=policy_kwargs, seed=0)
    model.learn(total_timesteps=128)
    observations = np.concatenate([env.step([env.action_space.sample()])[0] for _ in range(10)], axis=0)
    original = deepcopy(model.get_parameters())

    invalid = {**deepcopy(original), "not_an_object": "not a tensor"}
    for exact_match in (True, False):
        with pytest.raises(ValueError):
            model.set_parameters(invalid, exact_match=exact_match)
    with pytest.raises(ValueError):
        model.set_parameters(dict(list(original.items())[:-1]), exact_match=True)
    with pytest.raises(RuntimeError):
        model.set_parameters({name: dict(list(params.items())[:-1]) for name, params in original.items()}, exact_match=True)

    # random values for every tensor but the last of each state dict (optimizers as they were)
    random = {
        name: params if "optim" in name else OrderedDict((key, th.rand_like(value)) for key, value in list(params.items())[:-1])
        for name, params in original.items()
    }
    model.set_parameters(random, exact_match=False)
    changed = model.get_parameters()
    for name, params in original.items():
        if "optim" in name:
            continue
        last_key = list(params)[-1]
        for key, value in params.items():
            if key == last_key:
                assert th.allclose(value, changed[name][key]), f"{name}: {key} changed, but was not given"
            else:
                assert not th.allclose(value, changed[name][key]), f"{name}: {key} was given but did not change"

    actions, _ = model.predict(observations, deterministic=True)
    model.save(tmp_path / "model.zip")
    loaded = model_class.load(tmp_path / "model.zip", env=env, device="cpu")
    for name, params in loaded.get_parameters().items():
        if "optim" not in name:
            for key, value in params.items():
                assert th.allclose(changed[name][key], value), f"{name}: {key}"
    np.testing.assert_allclose(loaded.predict(observations, deterministic=True)[0], actions, rtol=1e-6, atol=1e-6)
