"""CrossQ's critics (``policy_kwargs=dict(critic="batch_renorm")``): batch renormalisation, no target networks."""

import pytest
import torch as th

from sb3_dacerf import DACER, DACERF
from sb3_dacerf.common.policies import BatchRenormCritic, EnsembleBatchRenorm

pytest.importorskip("sb3_contrib")


def batch_renorm_layers(critic: th.nn.Module) -> list[th.nn.Module]:
    return [module for module in critic.modules() if isinstance(module, EnsembleBatchRenorm)]


@pytest.fixture(params=[DACERF, DACER])
def model_class(request) -> type:
    return request.param


def test_critics_learn_without_targets_and_update_statistics_once_per_critic_update(model_class, fast):
    fast["policy_kwargs"]["critic"] = "batch_renorm"
    model = model_class("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    assert isinstance(model.critic, BatchRenormCritic)
    # one layer before each of the three linear layers, holding the statistics of both critics
    assert [layer.ra_mean.shape[0] for layer in batch_renorm_layers(model.critic)] == [2, 2, 2]
    target_before = {name: value.clone() for name, value in model.critic_target.state_dict().items()}
    critic_before = [param.clone() for param in model.critic.parameters()]
    model.learn(200)
    # the critics learned; their targets were never updated (nor used)
    assert any(not th.equal(before, after) for before, after in zip(critic_before, model.critic.parameters(), strict=True))
    for name, value in model.critic_target.state_dict().items():
        assert th.equal(value, target_before[name]), name
    for layer in batch_renorm_layers(model.critic):
        # the statistics moved in the critic update's joint pass only: not in the actor's or the Langevin targets' passes
        assert layer.steps.item() == model._n_updates == 150
        assert not th.equal(layer.ra_mean, th.zeros_like(layer.ra_mean))
        # and outside that pass the layers normalise with the running statistics
        assert not layer.training


@pytest.mark.parametrize("model_class", [DACERF])  # the fast settings follow model_class: DACERF's
def test_saved_and_loaded_with_their_running_statistics(tmp_path, fast):
    fast["policy_kwargs"]["critic"] = "batch_renorm"
    model = DACERF("MlpPolicy", "Pendulum-v1", seed=0, **fast)
    model.learn(100)
    model.save(tmp_path / "crossq")
    loaded = DACERF.load(tmp_path / "crossq")
    assert isinstance(loaded.critic, BatchRenormCritic)
    for layer, loaded_layer in zip(batch_renorm_layers(model.critic), batch_renorm_layers(loaded.critic), strict=True):
        assert th.equal(layer.ra_var, loaded_layer.ra_var) and not loaded_layer.training
    observations = th.rand((7, 3))
    actions = th.rand((7, 1)) * 2 - 1
    with th.no_grad():
        for q_value, loaded_q_value in zip(
            model.critic(observations, actions), loaded.critic(observations, actions), strict=True
        ):
            assert th.allclose(q_value, loaded_q_value)
