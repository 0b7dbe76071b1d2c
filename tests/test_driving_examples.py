"""Tests of the driving examples: training with progress, saving, resuming, and evaluating a saved model."""

import contextlib
import importlib.util
import io
import json
import os

import numpy as np
import pytest

pytest.importorskip("highway_env")

EXAMPLES = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples")


def load_example(name: str):
    spec = importlib.util.spec_from_file_location(name, os.path.join(EXAMPLES, f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SHORT = {"duration": 3}


@pytest.fixture(scope="module")
def trained_sac(tmp_path_factory):
    """A SAC driver trained for 200 steps with observation normalisation, saved by train_driving.py."""
    import torch

    torch.set_num_threads(1)
    save = str(tmp_path_factory.mktemp("models") / "sac")
    train = load_example("train_driving")
    args = ["--env", "multilane", "--algo", "sac", "--timesteps", "200", "--learning-starts", "100", "--batch-size", "32"]
    args += ["--config", json.dumps(SHORT), "--vec-normalize", "--save", save, "--eval-episodes", "1", "--log-interval", "100"]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        train.main(args)
    return save + "_multilane", out.getvalue()


@pytest.fixture(scope="module")
def trained(trained_sac):
    return trained_sac[0]


def test_train_prints_progress_and_saves_model_stats_and_metadata(trained_sac):
    trained_sac, out = trained_sac
    assert "training 200 steps on 1 env(s), observations normalised" in out
    # progress every 100 steps: episodes so far and their outcome rates (3 s episodes: several per 100 steps)
    progress = [line for line in out.splitlines() if "/200 steps" in line]
    assert len(progress) == 2 and all("episodes; last" in line and "off-road" in line for line in progress), out
    assert "off-road rate" in out.splitlines()[-1]
    for suffix in (".zip", ".json", "_vecnormalize.pkl"):
        assert os.path.isfile(trained_sac + suffix), suffix
    with open(trained_sac + ".json") as file:
        assert json.load(file) == {"env_id": "DACERF-Multilane-v0", "density": "normal", "config": SHORT, "algo": "sac"}


def test_evaluate_prints_the_paper_metrics(trained, capsys):
    evaluate = load_example("evaluate_driving")
    results = evaluate.main([trained + ".zip", "--episodes", "2"])
    out = capsys.readouterr().out
    assert "observations normalised with" in out and "_vecnormalize.pkl" in out
    assert "TAR" in out and "arrival rate" in out and "collision rate" in out and "off-road rate" in out
    assert set(results) == {"tar", "tar_std", "arrival_rate", "collision_rate", "off_road_rate", "episode_length"}
    assert 1 <= results["episode_length"] <= 30 and np.isfinite(results["tar"])
    for key in ("arrival_rate", "collision_rate", "off_road_rate"):
        assert results[key] in (0.0, 0.5, 1.0)
    # seeded: the same episodes again
    assert evaluate.main([trained, "--episodes", "2"]) == results


def test_evaluate_errors_name_the_problem(trained, tmp_path):
    evaluate = load_example("evaluate_driving")
    with pytest.raises(SystemExit, match=r"no model file.*train_driving.py --save"):
        evaluate.main([str(tmp_path / "missing.zip")])
    with pytest.raises(SystemExit, match=r"trained on DACERF-Multilane-v0.*--force"):
        evaluate.main([trained, "--env", "intersection"])
    with pytest.raises(SystemExit, match=r"cannot load.*check --algo"):
        evaluate.main([trained, "--algo", "dacerf"])
    with pytest.raises(SystemExit, match=r"observation_space has shape \(93,\).*\(87,\)"):
        evaluate.main([trained, "--config", '{"surrounding_vehicles": 7}'])
    with pytest.raises(SystemExit, match="no VecNormalize statistics file"):
        evaluate.main([trained, "--vec-normalize", str(tmp_path / "none.pkl")])


def test_train_resumes_from_a_saved_model(trained, capsys):
    train = load_example("train_driving")
    train.main(["--load", trained, "--timesteps", "50", "--eval-episodes", "1", "--log-interval", "0"])
    out = capsys.readouterr().out
    assert "resumed" in out and "at 200 steps" in out and "observations normalised" in out
    assert "trained 250 steps in total" in out
    with pytest.raises(SystemExit):  # argparse errors print the message and exit with status 2
        train.main(["--load", trained, "--env", "intersection", "--timesteps", "10"])
    assert "was trained on multilane: pass --env multilane" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        train.main(["--load", trained, "--algo", "dacerf", "--timesteps", "10"])
    assert "is a sac model: pass --algo sac" in capsys.readouterr().err


def test_evaluate_a_dacerf_model_without_metadata(tmp_path, capsys):
    """A DACERF model saved by model.save() (no metadata file): --env and --vec-normalize given explicitly."""
    import gymnasium as gym
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from sb3_dacerf import DACERF

    torch.set_num_threads(1)
    env = VecNormalize(DummyVecEnv([lambda: gym.make("DACERF-Intersection-v0", config=SHORT)]), norm_reward=False)
    model = DACERF("MlpPolicy", env, learning_starts=50, batch_size=32, langevin_steps=2, seed=0)
    model.learn(100)
    model.save(tmp_path / "driver")
    env.save(tmp_path / "stats.pkl")
    evaluate = load_example("evaluate_driving")
    with pytest.raises(SystemExit, match="scenario is unknown: pass --env"):
        evaluate.main([str(tmp_path / "driver.zip")])
    args = [str(tmp_path / "driver.zip"), "--env", "intersection", "--vec-normalize", str(tmp_path / "stats.pkl")]
    results = evaluate.main([*args, "--config", json.dumps(SHORT), "--episodes", "1"])
    assert "DACERF from" in capsys.readouterr().out and np.isfinite(results["tar"])
