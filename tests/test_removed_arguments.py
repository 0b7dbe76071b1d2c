"""
Arguments of earlier versions, given by a user or read from a saved model: each converts to its replacement with a
``FutureWarning`` naming it, or is refused with a ``ValueError`` that says what to use; none changes behaviour silently.
"""

import glob
import os
import warnings

import pytest
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_dacerf import DACERF
from sb3_dacerf.common.buffers import DemonstrationReplayBuffer

EXAMPLES = os.path.join(os.path.dirname(__file__), os.pardir, "examples", "models")
TINY = dict(buffer_size=1, policy_kwargs=dict(net_arch=[8]), seed=0)


def test_compile_langevin_is_ignored_with_a_warning():
    with pytest.warns(FutureWarning, match=r"compile_langevin=True\) was removed and is ignored"):
        model = DACERF("MlpPolicy", "Pendulum-v1", compile_langevin=True, **TINY)
    assert not hasattr(model, "compile_langevin")


def test_entropy_estimate_fit_is_dropped_with_a_warning_and_noise_is_refused():
    with pytest.warns(FutureWarning, match=r"entropy_estimate='fit'\) was removed: it is the only estimate"):
        DACERF("MlpPolicy", "Pendulum-v1", entropy_estimate="fit", **TINY)
    with pytest.raises(ValueError, match=r"entropy_estimate='noise'\) was removed"):
        DACERF("MlpPolicy", "Pendulum-v1", entropy_estimate="noise", **TINY)


def test_a_misspelt_argument_is_a_type_error():
    with pytest.raises(TypeError, match=r"DACERF.__init__\(\) got an unexpected keyword argument 'langevin_step'"):
        DACERF("MlpPolicy", "Pendulum-v1", langevin_step=5)


@pytest.mark.parametrize(
    "attribute, value, message",
    [
        ("entropy_estimate", "noise", r"entropy_estimate='noise'\) was removed.*custom_objects=dict\(entropy_estimate='fit'\)"),
        ("flow_matching_weights", "td3bc", r"'td3bc' was removed.*custom_objects=dict\(flow_matching_weights='gain'\)"),
    ],
)
def test_a_saved_model_with_a_removed_behaviour_is_refused_with_the_way_to_load_it(tmp_path, attribute, value, message):
    model = DACERF("MlpPolicy", "Pendulum-v1", **TINY)
    setattr(model, attribute, value)  # as a model saved by an earlier version holds it
    model.save(tmp_path / "old")
    with pytest.raises(ValueError, match=message):
        DACERF.load(tmp_path / "old")
    replacement = "fit" if attribute == "entropy_estimate" else "gain"
    loaded = DACERF.load(tmp_path / "old", custom_objects={attribute: replacement})
    assert getattr(loaded, attribute, replacement) == replacement
    for name, tensor in model.policy.state_dict().items():
        assert th.equal(tensor, loaded.policy.state_dict()[name]), name


def test_a_saved_model_with_the_removed_defaults_and_critic_booleans_loads_as_it_was(tmp_path):
    model = DACERF("MlpPolicy", "Pendulum-v1", **{**TINY, "policy_kwargs": dict(net_arch=[8], critic="mlp")})
    model.compile_langevin, model.entropy_estimate = False, "fit"
    model.policy_kwargs = {"net_arch": [8], "n_sampling_steps": 1, "critic_layer_norm": False}
    model.save(tmp_path / "old")
    with pytest.warns(FutureWarning, match=r"critic_layer_norm=False is deprecated.*dict\(critic='mlp'\)"):
        loaded = DACERF.load(tmp_path / "old")
    assert loaded.policy_kwargs == {"net_arch": [8], "n_sampling_steps": 1, "critic": "mlp"}
    assert not hasattr(loaded, "compile_langevin") and not hasattr(loaded, "entropy_estimate")
    # saved again, it holds this version's names
    loaded.save(tmp_path / "new")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert DACERF.load(tmp_path / "new").policy_kwargs["critic"] == "mlp"


def test_a_saved_model_with_compile_langevin_loads_with_a_warning(tmp_path):
    model = DACERF("MlpPolicy", "Pendulum-v1", **TINY)
    model.compile_langevin = True
    model.save(tmp_path / "old")
    with pytest.warns(FutureWarning, match="compile_langevin=True"):
        DACERF.load(tmp_path / "old")


@pytest.mark.parametrize("demonstration_targets", ["actions", "langevin"])
def test_a_saved_model_with_demonstration_targets_keeps_them_in_its_buffer(tmp_path, demonstration_targets):
    """A model saved with DACERF(demonstration_targets=...) loads with them in its DemonstrationReplayBuffer."""
    model = DACERF("MlpPolicy", "Pendulum-v1", replay_buffer_class=DemonstrationReplayBuffer, **TINY)
    model.demonstration_targets = demonstration_targets  # as a model saved by an earlier version holds it
    model.replay_buffer_kwargs = {"demonstration_fraction": 0.5}
    model.save(tmp_path / "old")
    loaded = DACERF.load(tmp_path / "old")
    assert isinstance(loaded.replay_buffer, DemonstrationReplayBuffer) and not hasattr(loaded, "demonstration_targets")
    assert loaded.replay_buffer.demonstration_targets == loaded.replay_buffer_kwargs["demonstration_targets"]
    assert loaded.replay_buffer.demonstration_targets == demonstration_targets


@pytest.mark.parametrize(
    "name", sorted(os.path.basename(path)[: -len(".zip")] for path in glob.glob(os.path.join(EXAMPLES, "*.zip")))
)
def test_the_shipped_drivers_load_without_a_deprecation_warning(name):
    """The drivers in examples/models are saved in this version's format: nothing to convert, nothing to warn about."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)
        warnings.simplefilter("error", DeprecationWarning)
        model = DACERF.load(os.path.join(EXAMPLES, f"{name}.zip"))
    assert model.policy_kwargs == {"n_sampling_steps": 1, "critic": "layer_norm"}
    if name.endswith("_rl"):
        # Trained purely by RL: SB3's own buffer, no demonstrations anywhere
        assert type(model.replay_buffer) is ReplayBuffer and model.replay_buffer_kwargs == {}
        return
    # The intersection driver fits the demonstrated actions, the multi-lane driver their Langevin targets
    expected = {"dacerf_intersection": "actions", "dacerf_multilane": "langevin"}[name]
    assert isinstance(model.replay_buffer, DemonstrationReplayBuffer)
    assert model.replay_buffer.demonstration_targets == model.replay_buffer_kwargs["demonstration_targets"] == expected
