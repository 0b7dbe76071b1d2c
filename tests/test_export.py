import pickle
import re
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import TABLE_ROWS, TableEnv
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import SimpleMultiObsEnv
from stable_baselines3.common.vec_env import VecNormalize

from sb3_dacerf import DACER, DACERF, DSAC
from sb3_dacerf.common.persistence import load_vec_normalize, save_vec_normalize
from sb3_dacerf.export import export_policy, exportable_policy, load_model, main

ort = pytest.importorskip("onnxruntime")

# Untrained tiny models: equivalence does not depend on training or size
TINY = dict(buffer_size=1, policy_kwargs=dict(net_arch=[32, 32]), seed=0)
# DACER with the linear noise schedule: an untrained model's deterministic actions are then inside the bounds (with
# the cosine schedule most are clipped, which would hide differences); the cosine schedule is tested on its own
TINY_DACER = dict(buffer_size=1, policy_kwargs=dict(net_arch=[32, 32], n_diffusion_steps=5), seed=0)


class DiscreteObsEnv(gym.Env):
    """Box actions from Discrete, MultiDiscrete, MultiBinary and Box observations: every kind SB3 preprocesses."""

    observation_space = spaces.Dict(
        {
            "discrete": spaces.Discrete(4),
            "multi_discrete": spaces.MultiDiscrete([2, 3]),
            "multi_binary": spaces.MultiBinary(3),
            "box": spaces.Box(-1.0, 1.0, (2,), dtype=np.float32),
        }
    )
    action_space = spaces.Box(np.array([-2.0, 0.0], dtype=np.float32), np.array([2.0, 5.0], dtype=np.float32))

    def reset(self, *, seed=None, options=None):
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


def make_model(policy: str, n_sampling_steps: int = 1, algorithm: type = DACERF):
    tiny_dacerf = {**TINY, "policy_kwargs": {**TINY["policy_kwargs"], "n_sampling_steps": n_sampling_steps}}
    settings = tiny_dacerf if algorithm is DACERF else dict(TINY_DACER)
    if algorithm is DSAC:
        settings = dict(TINY)
    if policy == "MlpPolicy":
        model = algorithm("MlpPolicy", "Pendulum-v1", **settings)
    else:
        env = SimpleMultiObsEnv(discrete_actions=False) if policy == "MultiInputPolicy" else DiscreteObsEnv()
        model = algorithm("MultiInputPolicy", env, **settings)
    if algorithm is DACER:  # a small predicted noise: the untrained reverse process then stays inside the bounds
        with th.no_grad():
            model.actor.network[-1].weight.mul_(0.05)
            model.actor.network[-1].bias.mul_(0.05)
    return model


def sample_observations(model, n: int):
    """``n`` observations of the model's space, batched (numpy) as the exported graph and ``predict`` take them."""
    samples = [model.observation_space.sample() for _ in range(n)]
    if isinstance(model.observation_space, spaces.Dict):
        return {key: np.stack([np.asarray(sample[key]) for sample in samples]) for key in samples[0]}
    return np.stack(samples)


def run_exported(path, format: str, obs, noise: np.ndarray | None = None, noise_name: str = "a0") -> np.ndarray:
    """Run an exported policy as a deployment would: onnxruntime, or the TorchScript file without this package."""
    if format == "onnx":
        feed = dict(obs) if isinstance(obs, dict) else {"obs": obs}
        if noise is not None:
            feed[noise_name] = noise
        return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, feed)[0]
    policy = th.jit.load(str(path))
    obs_tensor = {key: th.as_tensor(value) for key, value in obs.items()} if isinstance(obs, dict) else th.as_tensor(obs)
    with th.no_grad():
        return (policy(obs_tensor) if noise is None else policy(obs_tensor, th.as_tensor(noise))).numpy()


def sample_with_noise(model, obs, noise: np.ndarray) -> np.ndarray:
    """The stochastic policy with a given noise: ``actor.sample(features, noise)`` rescaled to the action space."""
    obs_tensor = model.policy.obs_to_tensor(obs)[0]
    with th.no_grad():
        features = model.actor.extract_features(obs_tensor, model.actor.features_extractor)
        actions = model.actor.sample(features, th.as_tensor(noise)).numpy()
    return model.policy.unscale_action(actions)


@pytest.mark.parametrize("format", ["onnx", "torchscript"])
@pytest.mark.parametrize("policy", ["MlpPolicy", "MultiInputPolicy", "DiscreteObs"])
@pytest.mark.parametrize("algorithm", [DACERF, DACER, DSAC], ids=["DACERF", "DACER", "DSAC"])
def test_exported_policy_matches_predict(tmp_path, format, policy, algorithm):
    model = make_model(policy, algorithm=algorithm)
    path = export_policy(model, tmp_path / "policy", format=format)
    obs = sample_observations(model, 200)
    expected, _ = model.predict(obs, deterministic=True)
    # Most actions inside the bounds: a difference would not be hidden by the clipping
    low, high = model.action_space.low, model.action_space.high
    assert ((expected > low + 1e-3) & (expected < high - 1e-3)).mean() > 0.5
    assert np.abs(run_exported(path, format, obs) - expected).max() <= 1e-5
    single = {key: value[:1] for key, value in obs.items()} if isinstance(obs, dict) else obs[:1]
    assert np.abs(run_exported(path, format, single) - expected[:1]).max() <= 1e-5

    # The noise as second input: the stochastic policy, one noise per observation or one for the whole batch
    noise_name = exportable_policy(model.actor).noise_name
    assert noise_name == ("a0" if algorithm is DACERF else "noise")
    noise = np.random.default_rng(0).standard_normal((200, *model.actor.noise_shape)).astype(np.float32)
    assert np.abs(run_exported(path, format, obs, noise, noise_name) - sample_with_noise(model, obs, noise)).max() <= 1e-5
    shared = np.repeat(noise[:1], 200, axis=0)
    assert np.abs(run_exported(path, format, obs, noise[:1], noise_name) - sample_with_noise(model, obs, shared)).max() <= 1e-5


@pytest.mark.parametrize("format", ["onnx", "torchscript"])
def test_exported_dacer_policy_with_the_cosine_schedule_and_default_settings(tmp_path, format):
    """DACER's default networks (3 x 256 Mish layers, 20 diffusion steps) and cosine schedule."""
    model = DACER("MlpPolicy", "Pendulum-v1", buffer_size=1, seed=0)
    path = export_policy(model, tmp_path / "policy", format=format)
    obs = sample_observations(model, 100)
    expected, _ = model.predict(obs, deterministic=True)
    assert np.abs(run_exported(path, format, obs) - expected).max() <= 1e-5
    noise = np.random.default_rng(1).standard_normal((100, 20, 1)).astype(np.float32)
    stochastic = sample_with_noise(model, obs, noise)
    assert (np.abs(stochastic) < 2 - 1e-3).mean() > 0.5  # mostly inside the bounds
    assert np.abs(run_exported(path, format, obs, noise, "noise") - stochastic).max() <= 1e-5


def test_dacer_number_of_steps_is_that_of_its_schedule(tmp_path):
    model = make_model("MlpPolicy", algorithm=DACER)
    export_policy(model, tmp_path / "p.onnx", n_sampling_steps=5)  # its own number of steps is accepted
    with pytest.raises(ValueError, match="runs the 5 reverse steps of the noise schedule it was trained with"):
        export_policy(model, tmp_path / "p.onnx", n_sampling_steps=3)


def test_dsac_takes_no_number_of_steps_and_loads_from_its_file(tmp_path):
    model = make_model("MlpPolicy", algorithm=DSAC)
    with pytest.raises(ValueError, match="a DSAC policy computes its action in one network call"):
        export_policy(model, tmp_path / "p.onnx", n_sampling_steps=1)
    model.save(tmp_path / "dsac.zip")
    assert isinstance(load_model(tmp_path / "dsac.zip"), DSAC)


@pytest.mark.parametrize("format", ["onnx", "torchscript"])
def test_number_of_euler_steps_is_fixed_at_export(tmp_path, format):
    model = make_model("MlpPolicy", n_sampling_steps=3)
    obs = sample_observations(model, 100)
    expected_3, _ = model.predict(obs, deterministic=True)
    assert np.abs(run_exported(export_policy(model, tmp_path / "n3", format), format, obs) - expected_3).max() <= 1e-5

    path = export_policy(model, tmp_path / "n5", format, n_sampling_steps=5)
    assert model.actor.n_sampling_steps == 3  # exporting does not change the model
    model.actor.n_sampling_steps = 5
    expected_5, _ = model.predict(obs, deterministic=True)
    assert np.abs(expected_5 - expected_3).max() > 1e-4  # the step count matters for this model
    assert np.abs(run_exported(path, format, obs) - expected_5).max() <= 1e-5


@pytest.mark.parametrize("format", ["onnx", "torchscript"])
@pytest.mark.parametrize("policy", ["MlpPolicy", "MultiInputPolicy"])
@pytest.mark.parametrize("algorithm", [DACERF, DACER, DSAC], ids=["DACERF", "DACER", "DSAC"])
def test_vec_normalize_statistics_are_baked_in(tmp_path, format, policy, algorithm):
    if policy == "MlpPolicy":
        vec_env = VecNormalize(make_vec_env("Pendulum-v1"), clip_obs=2.0)
    else:
        vec_env = VecNormalize(make_vec_env(lambda: SimpleMultiObsEnv(discrete_actions=False)), norm_obs_keys=["vec"])
    model = algorithm(policy, vec_env, **(TINY_DACER if algorithm is DACER else TINY))
    # Statistics far from (0, 1), so that forgetting or misapplying them shows
    rng = np.random.default_rng(0)
    obs_rms = vec_env.obs_rms if policy == "MlpPolicy" else vec_env.obs_rms["vec"]
    obs_rms.mean = rng.normal(size=obs_rms.mean.shape)
    obs_rms.var = rng.uniform(0.01, 4.0, size=obs_rms.var.shape)
    vec_env.save(str(tmp_path / "vecnormalize.pkl"))
    loaded = VecNormalize.load(str(tmp_path / "vecnormalize.pkl"), vec_env)

    path = export_policy(model, tmp_path / "policy", format, vec_normalize=loaded)
    obs = sample_observations(model, 200)
    expected, _ = model.predict(vec_env.normalize_obs(obs), deterministic=True)
    assert np.abs(run_exported(path, format, obs) - expected).max() <= 1e-5


@pytest.mark.parametrize("format", ["onnx", "torchscript"])
def test_masked_vec_normalize_is_baked_in(tmp_path, format):
    from stable_baselines3.common.vec_env import DummyVecEnv

    from sb3_dacerf.common.vec_normalize import MaskedVecNormalize

    vec_env = MaskedVecNormalize(DummyVecEnv([TableEnv]), rows=TABLE_ROWS, clip_obs=3.0)
    vec_env.seed(0)
    vec_env.reset()
    for _ in range(50):
        vec_env.step(np.zeros((1, 2), dtype=np.float32))
    model = DACERF("MlpPolicy", vec_env, **TINY)
    path = export_policy(model, tmp_path / "policy", format, vec_normalize=vec_env)
    table_env = TableEnv()
    table_env.reset(seed=1)
    obs = np.stack([table_env.observe() for _ in range(200)])
    assert (obs[:, 10] == 0).any() and (obs[:, 10] == 1).any()  # observations with and without a third row
    vec_env.training = False
    expected, _ = model.predict(vec_env.normalize_obs(obs), deterministic=True)
    assert np.abs(run_exported(path, format, obs) - expected).max() <= 1e-5


@pytest.mark.slow  # a subprocess
def test_command_line(tmp_path, monkeypatch, capsys):
    model = make_model("MlpPolicy")
    model.save(tmp_path / "model.zip")
    # A DACER model: the algorithm is read from the file (in-process: a subprocess start costs seconds)
    dacer = make_model("MlpPolicy", algorithm=DACER)
    dacer.save(tmp_path / "dacer.zip")
    monkeypatch.setattr(sys, "argv", ["export", str(tmp_path / "dacer.zip"), "--format", "torchscript"])
    main()
    assert "(torchscript, 5 diffusion step(s))" in capsys.readouterr().out
    obs = sample_observations(dacer, 50)
    expected, _ = dacer.predict(obs, deterministic=True)
    assert np.abs(run_exported(tmp_path / "dacer.pt", "torchscript", obs) - expected).max() <= 1e-5

    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "sb3_dacerf.export",
            str(tmp_path / "model.zip"),
            "--format",
            "onnx",
            "--out",
            str(tmp_path / "policy.onnx"),
        ],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    obs = sample_observations(model, 100)
    assert np.abs(run_exported(tmp_path / "policy.onnx", "onnx", obs) - model.predict(obs, deterministic=True)[0]).max() <= 1e-5

    # The failures in-process (a subprocess start costs seconds): a usage error, exit status 2, and a message
    SAC("MlpPolicy", "Pendulum-v1", buffer_size=1, policy_kwargs=dict(net_arch=[8])).save(tmp_path / "sac.zip")
    for arguments, message in [
        ([str(tmp_path / "missing.zip")], "no model file at"),
        ([str(tmp_path / "sac.zip")], "could not load"),
        ([str(tmp_path / "model.zip"), "--vec-normalize", str(tmp_path / "missing.pkl")], "no VecNormalize statistics file"),
        ([str(tmp_path / "model.zip"), "--out", str(tmp_path / "missing" / "policy.onnx")], "does not exist"),
        ([str(tmp_path / "dacer.zip"), "--n-sampling-steps", "2"], "leave n_sampling_steps out"),
    ]:
        monkeypatch.setattr(sys, "argv", ["export", *arguments])
        with pytest.raises(SystemExit) as exit_info:
            main()
        assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_clear_errors(tmp_path):
    model = make_model("MlpPolicy")
    with pytest.raises(TypeError, match="exports DACERF, DACER and DSAC models"):
        export_policy(SAC("MlpPolicy", "Pendulum-v1", buffer_size=1, policy_kwargs=dict(net_arch=[8])), tmp_path / "p.onnx")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        export_policy(model, tmp_path / "missing" / "p.onnx")
    with pytest.raises(ValueError, match="Unknown export format"):
        export_policy(model, tmp_path / "p.onnx", format="tflite")
    with pytest.raises(ValueError, match="n_sampling_steps"):
        export_policy(model, tmp_path / "p.onnx", n_sampling_steps=0)
    with pytest.raises(TypeError, match="vec_normalize must be a VecNormalize"):
        export_policy(model, tmp_path / "p.onnx", vec_normalize=dict(mean=0.0))
    # A custom policy may declare a space that SB3's preprocessing does not handle
    model.observation_space = spaces.Tuple([spaces.Box(-1.0, 1.0, (3,))])
    with pytest.raises(TypeError, match="Cannot export a policy for the observation space"):
        export_policy(model, tmp_path / "p.onnx")


@pytest.mark.parametrize("format", ["onnx", "torchscript"])
def test_failed_export_leaves_the_previous_file_intact(tmp_path, monkeypatch, format):
    model = make_model("MlpPolicy")
    path = export_policy(model, tmp_path / "policy", format)
    obs = sample_observations(model, 10)
    expected = run_exported(path, format, obs)

    def write_then_fail(obj, file, *args, **kwargs):
        with open(file, "wb") as output:
            output.write(b"\0" * 4096)
        raise OSError(28, "No space left on device")

    with th.no_grad():
        next(model.actor.parameters()).add_(1.0)  # another policy, whose export fails half-way
    if format == "onnx":
        monkeypatch.setattr(pytest.importorskip("onnx"), "save", write_then_fail)
    else:
        monkeypatch.setattr(th.jit, "save", write_then_fail)
    with pytest.raises(OSError, match="No space left"):
        export_policy(model, path, format)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left behind
    np.testing.assert_array_equal(run_exported(path, format, obs), expected)


class BoxObsEnv(gym.Env):
    """Box observations of a given size, Pendulum's action space."""

    action_space = spaces.Box(-2.0, 2.0, (1,), dtype=np.float32)

    def __init__(self, size: int):
        self.observation_space = spaces.Box(-1.0, 1.0, (size,), dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


def vec_normalize_file(tmp_path, env, name: str, **kwargs) -> str:
    path = str(tmp_path / name)
    save_vec_normalize(VecNormalize(make_vec_env(env), **kwargs), path)
    return path


def test_command_line_refuses_vec_normalize_statistics_of_another_observation_space(tmp_path, monkeypatch, capsys):
    # Pendulum's observations have 3 entries; each file below would bake wrong statistics or crash the export
    make_model("MlpPolicy").save(tmp_path / "model.zip")
    (tmp_path / "junk.json").write_bytes(b"not JSON")
    with open(tmp_path / "dict.pkl", "wb") as file:
        pickle.dump(dict(mean=0.0), file)
    for statistics, message in [
        # a 1-entry mean broadcasts over 3 entries: without the check, the export succeeded with wrong statistics
        (
            vec_normalize_file(tmp_path, lambda: BoxObsEnv(1), "one.json"),
            r"shape \(1,\) but the model's observations have shape \(3,\)",
        ),
        (
            vec_normalize_file(tmp_path, lambda: BoxObsEnv(5), "five.json"),
            r"shape \(5,\) but the model's observations have shape \(3,\)",
        ),
        (
            vec_normalize_file(tmp_path, lambda: SimpleMultiObsEnv(discrete_actions=False), "keys.json", norm_obs_keys=["vec"]),
            r"shape \{'vec': \(5,\)\} but the model's observations have shape \(3,\)",
        ),
        (str(tmp_path / "junk.json"), "could not read .*junk.json as observation statistics"),
        (str(tmp_path / "dict.pkl"), "is a pickle, which runs any code it holds when read"),
        (str(tmp_path / "dict.pkl") + " --unsafe-run-code-from-file", "vec_normalize must be a VecNormalize"),
    ]:
        statistics, *options = statistics.split()
        monkeypatch.setattr(sys, "argv", ["export", str(tmp_path / "model.zip"), "--vec-normalize", statistics, *options])
        with pytest.raises(SystemExit) as exit_info:
            main()
        error = capsys.readouterr().err
        assert exit_info.value.code == 2, error
        assert re.search(message, error), error
        assert "Traceback" not in error and not (tmp_path / "model.onnx").exists()


def test_dict_model_refuses_statistics_of_another_layout(tmp_path):
    model = make_model("MultiInputPolicy")
    box_statistics = VecNormalize(make_vec_env("Pendulum-v1"))
    with pytest.raises(ValueError, match=r"shape \(3,\) but the model's observations have shape \{.*'vec': \(5,\)"):
        export_policy(model, tmp_path / "p.onnx", vec_normalize=box_statistics)
    other_shape = VecNormalize(make_vec_env(lambda: SimpleMultiObsEnv(discrete_actions=False)), norm_obs_keys=["vec"])
    other_shape.obs_rms["vec"].mean = np.zeros(7)
    with pytest.raises(ValueError, match=r"shape \{'vec': \(7,\)\} but the model's observations have shape \{.*'vec': \(5,\)"):
        export_policy(model, tmp_path / "p.onnx", vec_normalize=other_shape)


MODELS = Path(__file__).resolve().parents[1] / "examples" / "models"


@pytest.mark.parametrize("stem", ["dacerf_multilane_rl", "dacerf_intersection_rl"])
def test_every_shipped_driver_exports_with_its_statistics(tmp_path, monkeypatch, capsys, stem):
    model = DACERF.load(MODELS / f"{stem}.zip", device="cpu")
    statistics = load_vec_normalize(MODELS / f"{stem}_vecnormalize.json")
    obs = np.random.default_rng(0).normal(size=(64, *model.observation_space.shape)).astype(np.float32)
    obs[:, -1] = 1.0  # (the last vehicle row present: MaskedVecNormalize keeps a mask entry of 1)
    expected = model.predict(statistics.normalize_obs(obs), deterministic=True)[0]
    for format, suffix in (("onnx", "onnx"), ("torchscript", "pt")):
        out = tmp_path / f"{stem}.{suffix}"
        arguments = [
            str(MODELS / f"{stem}.zip"),
            "--format",
            format,
            "--vec-normalize",
            str(MODELS / f"{stem}_vecnormalize.json"),
        ]
        monkeypatch.setattr(sys, "argv", ["export", *arguments, "--out", str(out)])
        main()
        assert f"to {out}" in capsys.readouterr().out
        assert np.abs(run_exported(out, format, obs) - expected).max() <= 1e-5


@pytest.mark.parametrize("policy", ["MlpPolicy", "MultiInputPolicy"])
def test_exported_policies_refuse_non_finite_observations(tmp_path, policy):
    """ONNX: the flag ``finite`` and NaN actions for those rows; TorchScript: an error."""
    model = make_model(policy)
    obs = sample_observations(model, 4)
    bad = {key: value.copy() for key, value in obs.items()} if isinstance(obs, dict) else obs.copy()
    array = bad["vec"] if isinstance(bad, dict) else bad
    array[1, 0], array[2, -1] = np.nan, np.inf
    expected = model.predict(obs, deterministic=True)[0]

    export_policy(model, tmp_path / "p.onnx")
    session = ort.InferenceSession(str(tmp_path / "p.onnx"), providers=["CPUExecutionProvider"])
    feed = dict(bad) if isinstance(bad, dict) else {"obs": bad}
    actions, finite = session.run(["action", "finite"], feed)
    assert finite.tolist() == [True, False, False, True]
    assert np.isnan(actions[[1, 2]]).all() and np.abs(actions[[0, 3]] - expected[[0, 3]]).max() <= 1e-5

    export_policy(model, tmp_path / "p.pt", format="torchscript")
    scripted = th.jit.load(str(tmp_path / "p.pt"))
    tensors = {key: th.as_tensor(value) for key, value in bad.items()} if isinstance(bad, dict) else th.as_tensor(bad)
    with pytest.raises(th.jit.Error, match="the observation has NaN or infinite entries"):
        scripted(tensors)
    for row in (0, 3):
        one = (
            {key: value[row : row + 1] for key, value in tensors.items()} if isinstance(tensors, dict) else tensors[row : row + 1]
        )
        assert np.abs(scripted(one).numpy() - expected[row]).max() <= 1e-5
