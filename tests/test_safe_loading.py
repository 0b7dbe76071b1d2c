"""
Files a user downloads run no code: crafted model zips, statistics pickles, metadata and configs go through every
loader (``load``, ``set_parameters``, the export command, ``examples/evaluate_driving.py``) and leave no trace of
code having run. Each payload, unpickled, would create a marker file. Also: the checksums of the shipped drivers,
and the validation of inputs that would otherwise pass silently (another environment's replay buffer, a zip missing
its parts, the temporary file of a killed save).
"""

import base64
import importlib.util
import io
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import fast_settings
from stable_baselines3 import SAC
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_dacerf import DACER, DACERF, DSAC
from sb3_dacerf.common.persistence import (
    CHECKSUMS,
    SAFE_ENTRY,
    UnsafeFileError,
    check_sha256,
    load_vec_normalize,
    read_sha256sums,
    safe_load,
    safe_save,
    save_vec_normalize,
    sha256,
)
from sb3_dacerf.common.vec_normalize import MaskedVecNormalize

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "examples" / "models"


def load_example(name: str):
    """The module of ``examples/<name>.py``."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


class Payload:
    """Unpickled, creates the file ``marker``: the trace a crafted file's code would leave."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def payload_bytes(marker: Path) -> bytes:
    return pickle.dumps(Payload(marker))


def rewrite_zip(source: Path, target: Path, replace: dict[str, bytes | None]) -> Path:
    """A copy of the zip ``source`` with entries replaced (``None``: left out)."""
    with zipfile.ZipFile(source) as original, zipfile.ZipFile(target, "w") as copy:
        for name in original.namelist():
            if name not in replace:
                copy.writestr(name, original.read(name))
        for name, content in replace.items():
            if content is not None:
                copy.writestr(name, content)
    return target


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("model") / "model.zip"
    DACERF("MlpPolicy", "Pendulum-v1", **fast_settings(DACERF)).save(path)
    return path


def crafted_zips(saved: Path, folder: Path, marker: Path) -> dict[str, Path]:
    """Model zips whose every pickled part (``data``'s objects, a ``.pth``) holds the payload."""
    with zipfile.ZipFile(saved) as archive:
        data = json.loads(archive.read("data"))
    encoded = base64.b64encode(payload_bytes(marker)).decode()
    for value in data.values():
        if isinstance(value, dict) and ":serialized:" in value:
            value[":serialized:"] = encoded
    with io.BytesIO() as buffer:
        th.save({"weights": Payload(marker)}, buffer)
        pth = buffer.getvalue()
    evil_entry = {"algorithm": "DACERF", "policy": "MlpPolicy", "objects": {"policy_kwargs": {"class": "os.system"}}}
    return {
        "data": rewrite_zip(saved, folder / "data.zip", {"data": json.dumps(data).encode()}),
        "data without sb3_dacerf.json": rewrite_zip(
            saved, folder / "bare.zip", {"data": json.dumps(data).encode(), SAFE_ENTRY: None}
        ),
        "policy.pth": rewrite_zip(saved, folder / "pth.zip", {"policy.pth": pth}),
        "pytorch_variables.pth": rewrite_zip(saved, folder / "variables.zip", {"pytorch_variables.pth": pth}),
        "class path in sb3_dacerf.json": rewrite_zip(saved, folder / "entry.zip", {SAFE_ENTRY: json.dumps(evil_entry).encode()}),
    }


def test_crafted_zips_run_no_code_in_load_or_set_parameters(saved, tmp_path):
    marker = tmp_path / "code-ran"
    model = DACERF("MlpPolicy", "Pendulum-v1", **fast_settings(DACERF))
    outcomes = {}
    for part, path in crafted_zips(saved, tmp_path, marker).items():
        loads = {
            "load": lambda path=path: DACERF.load(path),
            "load with custom_objects": lambda path=path: DACERF.load(path, custom_objects={"learning_rate": 0.0}),
            "safe_load as SAC": lambda path=path: safe_load(SAC, path),
            "set_parameters": lambda path=path: model.set_parameters(path),
        }
        for name, load in loads.items():
            try:
                load()
                outcomes[part, name] = "loaded"
            except ValueError as error:
                outcomes[part, name] = type(error).__name__
            assert not marker.exists(), f"code ran from a payload in {part} ({name})"
    # The pickles in data are never read: the weights and sb3_dacerf.json suffice
    assert outcomes["data", "load"] == outcomes["data", "set_parameters"] == "loaded"
    assert outcomes["data", "safe_load as SAC"] == "ValueError"  # a DACERF model
    assert outcomes["data without sb3_dacerf.json", "load"] == "UnsafeFileError"
    assert outcomes["policy.pth", "load"] == outcomes["policy.pth", "set_parameters"] == "UnsafeFileError"
    assert outcomes["pytorch_variables.pth", "load"] == "UnsafeFileError"
    assert outcomes["class path in sb3_dacerf.json", "load"] == "UnsafeFileError"


def test_unsafe_load_is_an_explicit_opt_in_that_runs_the_file(saved, tmp_path):
    marker = tmp_path / "code-ran"
    path = crafted_zips(saved, tmp_path, marker)["data without sb3_dacerf.json"]
    with pytest.raises(UnsafeFileError, match="unsafe_run_code_from_file=True, which runs any code"):
        DACERF.load(path)
    assert not marker.exists()
    with pytest.raises(Exception):  # noqa: B017  (the payload's object is no policy class)
        DACERF.load(path, unsafe_run_code_from_file=True)
    assert marker.exists()  # what the opt-in's name says


def test_safe_load_round_trip_rebuilds_what_sb3_pickles(tmp_path):
    """Spaces, train_freq, the replay buffer class and classes in policy_kwargs come back from JSON."""
    env = gym.make("Pendulum-v1")
    for cls in (DACERF, DACER, DSAC):
        settings = fast_settings(cls)
        settings["policy_kwargs"]["activation_fn"] = th.nn.Tanh
        model = cls("MlpPolicy", env, train_freq=(2, "step"), **settings)
        model.save(tmp_path / "model.zip")
        loaded = cls.load(tmp_path / "model.zip", env=env)
        obs = np.linspace(-1, 1, 3, dtype=np.float32)
        assert np.array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
        assert loaded.observation_space == model.observation_space and loaded.action_space == model.action_space
        assert loaded.train_freq == model.train_freq and loaded.policy_kwargs["activation_fn"] is th.nn.Tanh
        assert loaded.replay_buffer_class is model.replay_buffer_class
        loaded.learn(60)  # trains on


def test_safe_load_without_reset_goes_on_from_the_last_observation(tmp_path):
    """load(..., force_reset=False) keeps the rollout's last observations, as SB3's load does (a resumed training)."""
    model = DACERF("MlpPolicy", "Pendulum-v1", **fast_settings(DACERF))
    model.learn(60)
    model.save(tmp_path / "model.zip")
    loaded = DACERF.load(tmp_path / "model.zip", env=model.get_env(), force_reset=False)
    assert loaded._last_obs.dtype == model._last_obs.dtype and np.array_equal(loaded._last_obs, model._last_obs)
    assert np.array_equal(loaded._last_episode_starts, model._last_episode_starts)
    assert DACERF.load(tmp_path / "model.zip", env=model.get_env())._last_obs is None  # force_reset=True: a new episode


def test_known_schedules_come_back_and_others_need_custom_objects(tmp_path):
    from rl_zoo3.utils import linear_schedule
    from stable_baselines3.common.utils import LinearSchedule

    for schedule in (LinearSchedule(1e-3, 1e-4, 0.5), linear_schedule(3e-4)):  # SB3's, RL Zoo's lin_
        DSAC("MlpPolicy", "Pendulum-v1", learning_rate=schedule, **fast_settings(DSAC)).save(tmp_path / "model.zip")
        loaded = DSAC.load(tmp_path / "model.zip")
        assert type(loaded.learning_rate) is type(schedule)
        assert [loaded.lr_schedule(p) for p in (1.0, 0.3, 0.0)] == [schedule(p) for p in (1.0, 0.3, 0.0)]
    model = DSAC("MlpPolicy", "Pendulum-v1", learning_rate=lambda progress: 1e-3 * progress, **fast_settings(DSAC))
    model.save(tmp_path / "model.zip")
    with pytest.raises(UnsafeFileError, match=r"learning_rate .*custom_objects=\{'learning_rate': \.\.\.\}"):
        DSAC.load(tmp_path / "model.zip")
    loaded = DSAC.load(tmp_path / "model.zip", custom_objects={"learning_rate": 0.0})
    assert loaded.learning_rate == 0.0


def test_sac_saved_with_safe_save_loads_without_unpickling(tmp_path):
    model = SAC("MlpPolicy", "Pendulum-v1", learning_starts=10, policy_kwargs=dict(net_arch=[16]))
    safe_save(model, tmp_path / "sac.zip")
    loaded = safe_load(SAC, tmp_path / "sac.zip")
    obs = np.zeros(3, dtype=np.float32)
    assert np.array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    with pytest.raises(ValueError, match=r"holds a SAC model .*not a DACERF model: load it with SAC\.load"):
        DACERF.load(tmp_path / "sac.zip")


def test_a_zip_missing_its_parts_names_them(saved, tmp_path):
    for missing in ("policy.pth", "data"):
        path = rewrite_zip(saved, tmp_path / "partial.zip", {missing: None})
        with pytest.raises(ValueError, match=rf"missing {missing}.*save the model again"):
            DACERF.load(path)
    path = rewrite_zip(saved, tmp_path / "partial.zip", {"critic.optimizer.pth": None})
    with pytest.raises(ValueError, match=r"missing critic.optimizer.pth \(the optimizer state"):
        DACERF.load(path)
    (tmp_path / "not.zip").write_bytes(b"plain text")
    with pytest.raises(ValueError, match=r"wasn't a zip-file: load a model written by model\.save"):
        DACERF.load(tmp_path / "not.zip")


def test_another_environments_replay_buffer_is_refused(tmp_path):
    other = DACERF("MlpPolicy", "MountainCarContinuous-v0", **fast_settings(DACERF))
    other.learn(60)
    other.save_replay_buffer(tmp_path / "buffer.pkl")
    model = DACERF("MlpPolicy", "Pendulum-v1", **fast_settings(DACERF))
    own = model.replay_buffer
    with pytest.raises(
        ValueError, match=r"holds transitions of the observation_space Box.*load the buffer saved with this model"
    ):
        model.load_replay_buffer(tmp_path / "buffer.pkl")
    assert model.replay_buffer is own
    model.learn(60)  # trains on with its own buffer


def test_the_temporary_file_of_a_killed_save_is_removed_at_the_next_save(saved, tmp_path):
    target = tmp_path / "model.zip"
    script = textwrap.dedent(
        f"""
        import os, signal
        from sb3_dacerf.common.utils import atomic_path
        with atomic_path({str(target)!r}) as temporary:
            temporary.write_bytes(b"half a model")
            os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True)
    assert result.returncode == -signal.SIGKILL
    left = list(tmp_path.glob(".model.*.tmp.zip"))
    assert len(left) == 1
    # A temporary file of a writer that still runs is kept
    running = tmp_path / f".model.{os.getpid()}.abcdef.tmp.zip"
    running.write_bytes(b"being written")
    shutil.copy(saved, target)
    DACERF.load(target)
    assert not left[0].exists() and running.exists()
    left[0].write_bytes(b"half a model")
    DACERF("MlpPolicy", "Pendulum-v1", **fast_settings(DACERF)).save(target)
    assert not left[0].exists() and running.exists()


# Statistics and metadata


def test_statistics_round_trip_as_json(tmp_path):
    from sb3_dacerf.envs.driving.common.observation import vehicle_rows

    for cls in (VecNormalize, MaskedVecNormalize):
        venv = DummyVecEnv([lambda: gym.make("DACERF-Multilane-v0", config={"duration": 2})])
        kwargs = {"rows": vehicle_rows(venv.get_attr("config")[0])} if cls is MaskedVecNormalize else {}
        stats = cls(venv, **kwargs)
        stats.reset()
        for _ in range(5):
            stats.step(np.zeros((1, 2), dtype=np.float32))
        save_vec_normalize(stats, tmp_path / "stats.json")
        loaded = load_vec_normalize(tmp_path / "stats.json", venv)
        assert type(loaded) is cls
        obs = np.random.default_rng(0).normal(size=venv.observation_space.shape).astype(np.float32)
        assert np.array_equal(stats.normalize_obs(obs), loaded.normalize_obs(obs))
        assert np.array_equal(load_vec_normalize(tmp_path / "stats.json").normalize_obs(obs), loaded.normalize_obs(obs))


def test_a_statistics_pickle_is_not_read_as_json(tmp_path):
    marker = tmp_path / "code-ran"
    (tmp_path / "stats.pkl").write_bytes(payload_bytes(marker))
    with pytest.raises(ValueError, match="not observation statistics written by sb3_dacerf's save_vec_normalize"):
        load_vec_normalize(tmp_path / "stats.pkl")
    assert not marker.exists()


def test_a_config_class_path_is_not_imported(tmp_path, monkeypatch):
    marker = tmp_path / "code-ran"
    (tmp_path / "evil_vehicles.py").write_text(f"open({str(marker)!r}, 'w')\nclass Car: pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for env_id in ("DACERF-Multilane-v0", "DACERF-Intersection-v0"):
        with pytest.raises(ValueError, match=r"config\['other_vehicles_type'\] must be one of \['highway_env.vehicle"):
            gym.make(env_id, config={"other_vehicles_type": "evil_vehicles.Car"})
    assert not marker.exists() and "evil_vehicles" not in sys.modules
    gym.make("DACERF-Multilane-v0", config={"other_vehicles_type": "highway_env.vehicle.behavior.AggressiveVehicle"})


@pytest.fixture
def driver(tmp_path):
    """A copy of the shipped multi-lane driver (without its SHA256SUMS), to tamper with."""
    for suffix in (".zip", ".json", "_vecnormalize.json"):
        shutil.copy(MODELS / f"dacerf_multilane_rl{suffix}", tmp_path / f"driver{suffix}")
    return tmp_path / "driver"


def test_evaluate_reads_no_pickle_beside_the_model_and_no_module_from_the_metadata(driver, tmp_path, monkeypatch):
    evaluate = load_example("evaluate_driving")
    marker = tmp_path / "code-ran"
    os.remove(f"{driver}_vecnormalize.json")
    Path(f"{driver}_vecnormalize.pkl").write_bytes(payload_bytes(marker))
    with pytest.raises(SystemExit, match="beside the model is a pickle, which is not read unless asked for"):
        evaluate.load_driver(str(driver))
    with pytest.raises(SystemExit, match="is a pickle, which runs any code it holds when read"):
        evaluate.load_driver(str(driver), vec_normalize=f"{driver}_vecnormalize.pkl")
    assert not marker.exists()
    # An env id naming a module: never imported
    (tmp_path / "evil_envs.py").write_text(f"open({str(marker)!r}, 'w')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    metadata = json.loads(Path(f"{driver}.json").read_text())
    Path(f"{driver}.json").write_text(json.dumps({**metadata, "env_id": "evil_envs:Evil-v0"}))
    with pytest.raises(SystemExit, match=r"names the environment 'evil_envs:Evil-v0', none of \['DACERF-Multilane-v0'"):
        evaluate.load_driver(str(driver))
    Path(f"{driver}.json").write_text(json.dumps({**metadata, "config": {"other_vehicles_type": "evil_envs.Car"}}))
    with pytest.raises(ValueError, match="other_vehicles_type"):
        evaluate.load_driver(str(driver))
    assert not marker.exists() and "evil_envs" not in sys.modules


def test_evaluate_runs_no_code_from_a_crafted_model(driver, tmp_path):
    evaluate = load_example("evaluate_driving")
    marker = tmp_path / "code-ran"
    shutil.copy(f"{driver}.zip", tmp_path / "original.zip")
    for part, path in crafted_zips(tmp_path / "original.zip", tmp_path, marker).items():
        shutil.copy(path, f"{driver}.zip")
        if part == "data":  # its pickles are never read
            evaluate.load_driver(str(driver)).env.close()
        else:
            with pytest.raises(SystemExit, match="error: cannot load"):
                evaluate.load_driver(str(driver))
        assert not marker.exists(), part


def test_export_command_runs_no_code_from_crafted_files(saved, tmp_path, monkeypatch, capsys):
    from sb3_dacerf.export import main

    marker = tmp_path / "code-ran"
    (tmp_path / "stats.pkl").write_bytes(payload_bytes(marker))
    for part, path in crafted_zips(saved, tmp_path, marker).items():
        monkeypatch.setattr(sys, "argv", ["export", str(path), "--out", str(tmp_path / "x.onnx")])
        if part == "data":  # its pickles are never read
            main()
        else:
            with pytest.raises(SystemExit):
                main()
            assert "could not load" in capsys.readouterr().err
        assert not marker.exists(), part
    monkeypatch.setattr(sys, "argv", ["export", str(saved), "--vec-normalize", str(tmp_path / "stats.pkl")])
    with pytest.raises(SystemExit):
        main()
    assert "is a pickle, which runs any code it holds when read" in capsys.readouterr().err
    assert not marker.exists()


# Checksums of the shipped drivers


def test_every_shipped_driver_file_is_listed_in_sha256sums_and_matches():
    sums = read_sha256sums(MODELS)
    shipped = {path.name for path in MODELS.iterdir() if path.suffix in (".zip", ".json")}
    assert set(sums) == shipped
    for name, digest in sums.items():
        assert sha256(MODELS / name) == digest, name
        check_sha256(MODELS / name)
    assert not list(MODELS.glob("*.pkl"))


def test_a_changed_shipped_file_is_refused_by_the_loaders(tmp_path, monkeypatch, capsys):
    evaluate = load_example("evaluate_driving")
    shutil.copytree(MODELS, tmp_path / "models")
    stem = tmp_path / "models" / "dacerf_multilane_rl"
    stats = json.loads(Path(f"{stem}_vecnormalize.json").read_text())
    stats["clip_obs"] = 5.0
    Path(f"{stem}_vecnormalize.json").write_text(json.dumps(stats))
    with pytest.raises(SystemExit, match=rf"does not match its checksum in .*{CHECKSUMS}"):
        evaluate.load_driver(str(stem))
    from sb3_dacerf.export import main

    monkeypatch.setattr(sys, "argv", ["export", f"{stem}.zip", "--vec-normalize", f"{stem}_vecnormalize.json"])
    with pytest.raises(SystemExit):
        main()
    assert "does not match its checksum" in capsys.readouterr().err


# Inputs that would otherwise pass silently


@pytest.mark.parametrize("buffer_size", [0, -1])
def test_buffer_size_below_one_is_refused(model_class, buffer_size):
    settings = {**fast_settings(model_class), "buffer_size": buffer_size}
    with pytest.raises(ValueError, match=rf"Invalid buffer_size={buffer_size}: it must be a positive integer"):
        model_class("MlpPolicy", "Pendulum-v1", **settings)


@pytest.mark.slow  # RL Zoo in a subprocess
def test_buffer_size_below_one_in_rl_zoo_yaml_is_refused(tmp_path):
    from test_zoo import zoo_command

    command, env = zoo_command(
        "train", "--algo", "dacerf", "--env", "Pendulum-v1", "-n", "100", "-f", "logs", "-params", "buffer_size:0"
    )
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))  # this checkout's package
    result = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode != 0 and "Invalid buffer_size=0: it must be a positive integer" in result.stderr


def test_a_learning_rate_schedule_that_goes_negative_raises_when_it_does(model_class):
    settings = {**fast_settings(model_class), "learning_starts": 20}
    model = model_class("MlpPolicy", "Pendulum-v1", learning_rate=lambda progress: 1e-3 * (2 * progress - 1), **settings)
    with pytest.raises(ValueError, match=r"learning-rate schedule gave -[0-9.e-]+ at progress remaining 0\.4"):
        model.learn(100)
    assert 50 <= model.num_timesteps <= 52  # the first update past the middle of training
