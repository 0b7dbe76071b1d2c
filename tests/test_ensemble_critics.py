"""Ensemble critics: each layer of all the critics in one batched product, equal to separate critic networks."""

import functools
from collections import OrderedDict
from copy import deepcopy

import numpy as np
import pytest
import torch as th
from conftest import autograd_action_gradient
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
    twin_critic_loss,
)
from sb3_dacerf.common.twin_critic import frozen
from sb3_dacerf.dacerf.dacerf import actor_loss_weights, flow_matching_loss, langevin_targets

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


def test_ensemble_linear_holds_and_computes_as_its_linear_layers():
    linears = [nn.Linear(5, 4) for _ in range(3)]
    ensemble = EnsembleLinear(linears)
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
    with th.no_grad():
        next_actions = model.actor(batch.next_observations)
    critic_loss = twin_critic_loss(model.critic, model.critic_target, batch, next_actions, model.gamma)
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
    assert th.allclose(critic_loss, loss, rtol=1e-5, atol=1e-5)
    model.critic.optimizer.zero_grad()
    critic_loss.backward()
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
            autograd_action_gradient(min_q),  # the reference: autograd through the separate networks
            batch.actions,
            model.langevin_steps,
            model.langevin_step_size,
            model.langevin_temperature,
        )
        with th.no_grad():
            q_star, q_buffer = min_q(targets), min_q(batch.actions)
        actor_features = model.actor.extract_features(batch.observations, model.actor.features_extractor)
        q_pi = min_q(model.actor.sample(actor_features, model.actor.draw_noise(actor_features)))
        kappa, lambda_f = actor_loss_weights(model.flow_matching_weights, q_star, q_buffer, model.flow_matching_coef)
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
