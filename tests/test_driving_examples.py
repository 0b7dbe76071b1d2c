"""
Tests of the driving examples: training with progress, saving, resuming, evaluating a saved model, exporting a
learning_curves checkpoint to that format (benchmarks/export_driver.py) and rendering a trained driver.
"""

import contextlib
import glob
import importlib.util
import io
import json
import os
import sys
import zipfile

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("highway_env")
pytestmark = pytest.mark.slow  # the example scripts, run end to end

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXAMPLES = os.path.join(ROOT, "examples")
BENCHMARKS = os.path.join(ROOT, "benchmarks")


def load_example(name: str, folder: str = EXAMPLES):
    spec = importlib.util.spec_from_file_location(name, os.path.join(folder, f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
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
    lines = out.splitlines()
    assert "off-road rate" in lines[-3] and lines[-2].startswith("  TAR by outcome: ")
    assert lines[-1].startswith("  reward per episode by term: ") and "collision" in lines[-1], lines[-1]
    for suffix in (".zip", ".json", "_vecnormalize.json"):
        assert os.path.isfile(trained_sac + suffix), suffix
    with open(trained_sac + ".json") as file:
        assert json.load(file) == {"env_id": "DACERF-Multilane-v0", "density": "normal", "config": SHORT, "algo": "sac"}


def test_evaluate_prints_the_paper_metrics(trained, capsys):
    evaluate = load_example("evaluate_driving")
    results = evaluate.main([trained + ".zip", "--episodes", "2"])
    out = capsys.readouterr().out
    assert "observations normalised with" in out and "_vecnormalize.json" in out
    assert "TAR" in out and "arrival rate" in out and "collision rate" in out and "off-road rate" in out
    assert set(results) == {
        "tar",
        "tar_std",
        "arrival_rate",
        "collision_rate",
        "off_road_rate",
        "episode_length",
        "lateral_error",
        "speed_error",
        "by_outcome",
        "reward_terms",
    }
    assert 1 <= results["episode_length"] <= 30 and np.isfinite(results["tar"])
    assert results["lateral_error"] >= 0 and results["speed_error"] >= 0 and "distance to the reference path" in out
    for key in ("arrival_rate", "collision_rate", "off_road_rate"):
        assert results[key] in (0.0, 0.5, 1.0)
    # seeded: the same episodes again
    assert evaluate.main([trained, "--episodes", "2"]) == results


def test_evaluate_the_scripted_driver(capsys):
    evaluate = load_example("evaluate_driving")
    args = ["--scripted", "--env", "multilane", "--episodes", "2", "--config", json.dumps(SHORT)]
    results = evaluate.main(args)
    out = capsys.readouterr().out
    assert out.startswith("ScriptedDriver; DACERF-Multilane-v0 (normal), seeds 10000-10001")
    # the reference tracker stays close to its path: under the lane width on average
    assert results["episode_length"] >= 1 and 0 <= results["lateral_error"] < 4.0
    assert evaluate.main(args) == results and "by_route" not in results  # the highway has no routes
    with pytest.raises(SystemExit):
        evaluate.main(["--scripted"])
    assert "--scripted evaluates a baseline driver" in capsys.readouterr().err
    junction = evaluate.main(
        ["--scripted", "junction", "--env", "intersection", "--episodes", "2", "--config", json.dumps(SHORT)]
    )
    assert capsys.readouterr().out.startswith("JunctionDriver; DACERF-Intersection-v0 (normal), seeds 10000-10001")
    assert junction["episode_length"] >= 1
    with pytest.raises(SystemExit):
        evaluate.main(["--scripted", "junction", "--env", "multilane"])
    assert "--scripted junction drives the intersection" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        evaluate.main([])
    assert "pass a model .zip to evaluate" in capsys.readouterr().err


def test_evaluate_zero_increments(capsys):
    evaluate = load_example("evaluate_driving")
    args = ["--idle", "--env", "intersection", "--episodes", "2", "--config", json.dumps(SHORT)]
    results = evaluate.main(args)
    assert capsys.readouterr().out.startswith("Zero increments; DACERF-Intersection-v0 (normal), seeds 10000-10001")
    assert results["episode_length"] >= 1 and evaluate.main(args) == results
    # The same episodes as an env stepped with zero increments by hand, from the standard starts
    env = gym.make("DACERF-Intersection-v0", config={**SHORT, "reference_start_probability": 0.0})
    total = 0.0
    for seed in (10_000, 10_001):
        env.reset(seed=seed)
        done = False
        while not done:
            _obs, reward, terminated, truncated, _info = env.step(np.zeros(2, dtype=np.float32))
            total += reward
            done = terminated or truncated
    assert results["tar"] == pytest.approx(total / 2)
    with pytest.raises(SystemExit):
        evaluate.main(["--idle", "--scripted", "--env", "multilane"])
    assert "two baselines" in capsys.readouterr().err


def test_evaluate_breaks_the_intersection_down_by_route(capsys):
    evaluate = load_example("evaluate_driving")
    results = evaluate.main(["--scripted", "--env", "intersection", "--episodes", "4", "--config", json.dumps(SHORT)])
    by_route = results["by_route"]
    assert set(by_route) <= {"straight", "left", "right", "u_turn"}
    assert sum(rates["episodes"] for rates in by_route.values()) == 4
    # the overall rates are the episode-weighted means of the routes' rates
    for key in ("arrival_rate", "collision_rate", "off_road_rate"):
        weighted = sum(rates["episodes"] * rates[key] for rates in by_route.values()) / 4
        assert weighted == pytest.approx(results[key])
    out = capsys.readouterr().out
    assert all(f"  {route}: {rates['episodes']} episodes, arrival" in out for route, rates in by_route.items())
    # the episodes split by how they ended: counts and TAR add up to the whole, and the rates agree with the counts
    by_outcome = results["by_outcome"]
    assert set(by_outcome) <= {"arrival", "collision", "off road", "time limit"}
    assert sum(part["episodes"] for part in by_outcome.values()) == 4
    assert sum(part["episodes"] * part["tar"] for part in by_outcome.values()) / 4 == pytest.approx(results["tar"])
    assert by_outcome.get("arrival", {"episodes": 0})["episodes"] == round(4 * results["arrival_rate"])
    assert sum(part["episodes"] * part["episode_length"] for part in by_outcome.values()) / 4 == pytest.approx(
        results["episode_length"]
    )
    assert "  TAR by outcome: " in out
    # the reward's terms, summed per episode, add up to the TAR
    assert sum(results["reward_terms"].values()) == pytest.approx(results["tar"])
    assert "  reward per episode by term: " in out


def test_shipped_drivers_load_and_drive(capsys):
    # every driver in examples/models loads with its metadata and statistics and drives a short seeded episode
    evaluate = load_example("evaluate_driving")
    stems = sorted(path[: -len(".zip")] for path in glob.glob(os.path.join(EXAMPLES, "models", "*.zip")))
    assert stems, "examples/models holds no driver"
    for stem in stems:
        results = evaluate.main([stem, "--episodes", "1", "--config", json.dumps(SHORT)])
        assert results["episode_length"] >= 1 and np.isfinite(results["tar"])
        assert "observations normalised with" in capsys.readouterr().out


def test_evaluations_start_from_the_standard_starts(tmp_path):
    """
    At the intersection an evaluation starts before the junction (EVALUATION_CONFIG) whatever the metadata's config
    says: a driver trained from the traffic flow drives the same episodes as one without the key; --config still sets it.
    """
    import shutil

    evaluate = load_example("evaluate_driving")
    shipped, stem = os.path.join(EXAMPLES, "models", "dacerf_intersection_rl"), str(tmp_path / "trained_in_the_flow")
    for suffix in (".zip", "_vecnormalize.json"):
        shutil.copy(shipped + suffix, stem + suffix)
    with open(shipped + ".json") as file:
        metadata = json.load(file)
    assert "reference_start_probability" not in metadata["config"]
    metadata["config"]["reference_start_probability"] = 0.5
    with open(stem + ".json", "w") as file:
        json.dump(metadata, file)
    assert evaluate.load_driver(stem).env.unwrapped.config["reference_start_probability"] == 0.0
    explicit = evaluate.load_driver(stem, config={"reference_start_probability": 1.0})
    assert explicit.env.unwrapped.config["reference_start_probability"] == 1.0
    args = ["--episodes", "2", "--config", json.dumps(SHORT)]
    assert evaluate.main([stem, *args]) == evaluate.main([shipped, *args])
    assert evaluate.evaluation_config("DACERF-Multilane-v0", {"duration": 5}, {"duration": 3}) == {"duration": 3}


def test_train_on_drawn_densities_with_masked_normalisation_and_evaluate_at_each(tmp_path, capsys):
    """train_driving.py --density random --vec-normalize masked; evaluate_driving.py --density all prints one table."""
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv

    from sb3_dacerf.common.persistence import load_vec_normalize
    from sb3_dacerf.common.vec_normalize import MaskedVecNormalize

    torch.set_num_threads(1)
    train, evaluate = load_example("train_driving"), load_example("evaluate_driving")
    save = str(tmp_path / "mixed")
    args = ["--env", "multilane", "--algo", "sac", "--timesteps", "100", "--learning-starts", "50", "--batch-size", "16"]
    args += ["--config", json.dumps(SHORT), "--density", "random", "--vec-normalize", "masked", "--save", save]
    train.main([*args, "--eval-episodes", "1", "--log-interval", "0"])
    assert "DACERF-Multilane-v0 (random), sac, training 100 steps on 1 env(s), observations normalised (MaskedVecNormalize)" in (
        capsys.readouterr().out
    )
    with open(save + "_multilane.json") as file:
        assert json.load(file)["density"] == "random"
    stats = load_vec_normalize(save + "_multilane_vecnormalize.json", DummyVecEnv([lambda: gym.make("DACERF-Multilane-v0")]))
    assert isinstance(stats, MaskedVecNormalize)

    results = evaluate.main([save + "_multilane", "--density", "all", "--episodes", "2", "--seed", "5"])
    out = capsys.readouterr().out
    assert set(results) == {"sparse", "normal", "dense"}
    table = out[out.index("| density |") :].splitlines()
    assert len(table) == 5 and [line.split(" | ")[0] for line in table[2:]] == ["| sparse", "| normal", "| dense"]
    assert "| arrival | collision | off road |" in table[0]
    # each row is the evaluation at that density on the same seeds
    assert evaluate.main([save + "_multilane", "--density", "dense", "--episodes", "2", "--seed", "5"]) == results["dense"]
    # a baseline at every density, and densities drawn per episode
    scripted = evaluate.main(
        ["--scripted", "--env", "multilane", "--density", "all", "--episodes", "1", "--config", json.dumps(SHORT)]
    )
    assert set(scripted) == {"sparse", "normal", "dense"}
    drawn = evaluate.main(
        ["--scripted", "--env", "multilane", "--density", "sparse,dense", "--episodes", "2", "--config", json.dumps(SHORT)]
    )
    assert drawn["episode_length"] >= 1
    capsys.readouterr()
    for bad, message in (
        ("heavy", "Unknown density 'heavy'"),
        ("sparse,sparse", "lists 'sparse' more than once"),
        ('{"sparse": -1}', "the weight of 'sparse' must be a finite number >= 0"),
        ("{sparse", "is not a JSON dict of weights"),
    ):
        with pytest.raises(SystemExit):
            evaluate.main(["--scripted", "--env", "multilane", "--density", bad])
        assert message in capsys.readouterr().err
    with pytest.raises(SystemExit):
        train.main(["--env", "multilane", "--density", "all"])
    assert "to train on all of them, pass --density random" in capsys.readouterr().err


def test_zero_empty_rows_changes_only_the_empty_rows(trained, capsys):
    """--zero-empty-rows: empty vehicle rows get zeros after VecNormalize, present rows keep their normalisation."""
    evaluate = load_example("evaluate_driving")
    plain = evaluate.load_driver(trained, density="sparse")
    zeroed = evaluate.load_driver(trained, density="sparse", zero_empty_rows=True)
    assert plain.empty_rows is None and zeroed.empty_rows == (45, 8, 6)
    obs, _ = plain.env.reset(seed=0)
    table = obs[45:].reshape(8, 6)
    assert (table[:, 5] == 0).any() and (table[:, 5] == 1).any()  # sparse traffic: both kinds of rows
    seen = []
    zeroed.model.predict = lambda normalized, deterministic: (seen.append(normalized) or np.zeros(2), None)
    zeroed.act(obs)
    expected = plain.vec_normalize.normalize_obs(obs)
    expected[45:].reshape(8, 6)[table[:, 5] == 0] = 0.0
    np.testing.assert_array_equal(seen[0], expected)
    results = evaluate.main([trained, "--density", "sparse", "--episodes", "1", "--zero-empty-rows"])
    assert "empty vehicle rows zeroed" in capsys.readouterr().out and results["episode_length"] >= 1
    with pytest.raises(SystemExit):
        evaluate.main(["--scripted", "--env", "multilane", "--zero-empty-rows"])
    assert "--zero-empty-rows changes a model's normalised observations" in capsys.readouterr().err


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
    with pytest.raises(SystemExit, match="no statistics file"):
        evaluate.main([trained, "--vec-normalize", str(tmp_path / "none.json")])


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


def test_train_at_steps_per_gradient(trained, tmp_path, capsys):
    """--steps-per-gradient S: S transitions per gradient step (train_freq S / n_envs); both counts printed."""
    from stable_baselines3 import SAC

    train = load_example("train_driving")
    save = str(tmp_path / "regime")
    args = ["--env", "multilane", "--algo", "sac", "--timesteps", "80", "--learning-starts", "40", "--batch-size", "16"]
    args += ["--config", json.dumps(SHORT), "--eval-episodes", "1", "--log-interval", "40", "--save", save]
    train.main([*args, "--steps-per-gradient", "4", "--n-envs", "2", "--vec-env", "dummy"])
    out = capsys.readouterr().out
    # rollouts of 2 steps of 2 envs; one gradient step after each that ends beyond 40 transitions: 44, 48, ..., 80
    assert "training 80 steps on 2 env(s), 1 gradient step(s) every 4 steps" in out
    # the progress line at 80 steps comes before that rollout's gradient step
    assert "40/80 steps, " in out and "80/80 steps, " in out and ", 9 gradient steps (" in out
    assert "trained 80 steps in total (10 gradient steps)" in out
    model = SAC.load(save + "_multilane.zip")
    assert (model.train_freq.frequency, model.gradient_steps) == (2, 1)
    # below 1 transition per gradient step, in other processes; --load takes a new regime
    train.main(
        ["--load", trained, "--timesteps", "20", "--eval-episodes", "1", "--log-interval", "0", "--steps-per-gradient", "1/2"]
    )
    assert "2 gradient step(s) every 1 steps" in capsys.readouterr().out
    train.main([*args, "--steps-per-gradient", "2", "--n-envs", "2", "--vec-env", "subproc", "--timesteps", "60"])
    assert "trained 60 steps in total (10 gradient steps)" in capsys.readouterr().out
    for regime, message in (
        (["--steps-per-gradient", "3", "--n-envs", "2"], "3 environment steps per gradient step is not a multiple of n_envs 2"),
        (["--steps-per-gradient", "0"], "must be positive"),
    ):
        with pytest.raises(SystemExit):
            train.main([*args, *regime])
        assert message in capsys.readouterr().err


def test_train_at_the_intersection_evaluates_from_the_standard_starts(tmp_path, capsys, monkeypatch):
    """Training starts in the traffic flow (the default), the final evaluation from the standard starts."""
    from stable_baselines3 import SAC

    train = load_example("train_driving")
    save = str(tmp_path / "sac")
    args = ["--env", "intersection", "--algo", "sac", "--timesteps", "50", "--learning-starts", "10", "--batch-size", "16"]
    args += ["--config", json.dumps(SHORT), "--eval-episodes", "1", "--log-interval", "0"]
    evaluated_configs, evaluate = [], train.evaluate

    def recording_evaluate(act, env, *args, **kwargs):
        evaluated_configs.append(env.unwrapped.config)
        return evaluate(act, env, *args, **kwargs)

    monkeypatch.setattr(train, "evaluate", recording_evaluate)
    train.main([*args, "--save", save, "--save-replay-buffer"])
    assert "trained 50 steps in total" in capsys.readouterr().out
    assert evaluated_configs[0]["reference_start_probability"] == 0.0 and evaluated_configs[0]["duration"] == 3
    model = SAC.load(save + "_intersection.zip")
    model.load_replay_buffer(save + "_intersection_replay_buffer.pkl")
    assert model.replay_buffer.pos == 50


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
    with pytest.raises(SystemExit, match="is a pickle, which runs any code it holds when read"):
        evaluate.main([*args, "--config", json.dumps(SHORT), "--episodes", "1"])
    # VecNormalize.save's pickle, read only when asked for
    results = evaluate.main([*args, "--config", json.dumps(SHORT), "--episodes", "1", "--unsafe-run-code-from-file"])
    assert "DACERF from" in capsys.readouterr().out and np.isfinite(results["tar"])


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """
    A learning_curves checkpoint (benchmarks/learning_curves.py's save_checkpoint) of a DACERF driver trained for
    100 steps with observation normalisation, in the folder layout <out>/checkpoints/<env>/<variant>-seed<N>.
    """
    import gymnasium as gym
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from sb3_dacerf import DACERF

    torch.set_num_threads(1)
    learning_curves = load_example("learning_curves", BENCHMARKS)
    env = VecNormalize(DummyVecEnv([lambda: gym.make("DACERF-Multilane-v0", config=SHORT)]), norm_reward=False)
    model = DACERF("MlpPolicy", env, learning_starts=50, batch_size=32, buffer_size=1_000, langevin_steps=2, seed=0)
    model.learn(100)
    out = tmp_path_factory.mktemp("results")
    folder = learning_curves.checkpoint_dir(out, "DACERF-Multilane-v0", "dacerf", 0)
    learning_curves.save_checkpoint(model, folder, [], 1.0)
    return folder, model, env


@pytest.fixture(scope="module")
def exported(checkpoint, tmp_path_factory):
    export = load_example("export_driver", BENCHMARKS)
    stem = str(tmp_path_factory.mktemp("shipped") / "driver")
    export.main([str(checkpoint[0]), stem])
    return stem


def test_export_writes_the_files_evaluate_driving_reads(checkpoint, exported, tmp_path, capsys):
    from sb3_dacerf import DACERF

    folder, model, env = checkpoint
    with open(exported + ".json") as file:
        assert json.load(file) == {"env_id": "DACERF-Multilane-v0", "density": "normal", "config": SHORT, "algo": "dacerf"}
    # No replay buffer, no optimizer moments: the policy and the optimizers' settings only
    with zipfile.ZipFile(exported + ".zip") as archive:
        assert "replay_buffer.pkl" not in archive.namelist()
    loaded = DACERF.load(exported + ".zip", device="cpu")
    for optimizer in (loaded.actor.optimizer, loaded.critic.optimizer, loaded.ent_coef_optimizer):
        assert len(optimizer.state) == 0 and optimizer.param_groups[0]["lr"] == model.learning_rate
    obs = np.random.default_rng(0).normal(size=(4, *model.observation_space.shape)).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    export = load_example("export_driver", BENCHMARKS)
    export.main([str(folder), str(tmp_path / "with_optimizer"), "--keep-optimizer"])
    assert os.path.getsize(exported + ".zip") < os.path.getsize(tmp_path / "with_optimizer.zip")
    assert len(DACERF.load(tmp_path / "with_optimizer.zip", device="cpu").actor.optimizer.state) > 0

    evaluate = load_example("evaluate_driving")
    capsys.readouterr()
    results = evaluate.main([exported, "--episodes", "1"])
    assert "observations normalised with" in capsys.readouterr().out and np.isfinite(results["tar"])
    with pytest.raises(SystemExit, match=r"cannot load .* as SAC \(.*holds a DACERF model .*not a SAC model.*\): check --algo"):
        evaluate.main([exported, "--algo", "sac"])
    stats = evaluate.load_driver(exported).vec_normalize
    assert not stats.training
    np.testing.assert_array_equal(stats.obs_rms.mean, env.obs_rms.mean)


def test_export_errors_name_the_problem(checkpoint, tmp_path):
    import gymnasium as gym
    from stable_baselines3 import SAC, TD3

    export = load_example("export_driver", BENCHMARKS)
    folder = checkpoint[0]
    with pytest.raises(SystemExit, match=r"is not a folder: pass a run's folder <out>/checkpoints/<env>/<variant>-seed<N>"):
        export.main([str(tmp_path / "missing"), str(tmp_path / "model")])
    # the env's folder, one level above the runs: the runs below are named
    with pytest.raises(SystemExit, match=r"is not a learning_curves checkpoint \(no model.zip or env.pkl\).*dacerf-seed0"):
        export.main([str(folder.parent), str(tmp_path / "model")])
    with pytest.raises(SystemExit, match=r"model.zip holds a dacerf model, not sac: leave out --algo"):
        export.main([str(folder), str(tmp_path / "model"), "--algo", "sac"])
    with pytest.raises(SystemExit, match=r"gym.make keyword arguments \['render'\].*density and config only"):
        export.main([str(folder), str(tmp_path / "model"), "--env-kwargs", '{"render": 1}'])
    with pytest.raises(SystemExit, match=r"observation shape is \(93,\), DACERF-Multilane-v0 with .* has \(87,\)"):
        export.main([str(folder), str(tmp_path / "model"), "--env-kwargs", '{"config": {"surrounding_vehicles": 7}}'])
    assert not os.path.exists(tmp_path / "model.zip")  # nothing written
    # runs of another environment or of an algorithm evaluate_driving.py does not load
    learning_curves = load_example("learning_curves", BENCHMARKS)
    pendulum = learning_curves.checkpoint_dir(tmp_path, "Pendulum-v1", "sac", 0)
    model = SAC("MlpPolicy", gym.make("Pendulum-v1"), buffer_size=100, policy_kwargs=dict(net_arch=[8]))
    learning_curves.save_checkpoint(model, pendulum, [], 0.0)
    with pytest.raises(SystemExit, match=r"a run of 'Pendulum-v1', not a driving scenario"):
        export.main([str(pendulum), str(tmp_path / "model")])
    td3 = learning_curves.checkpoint_dir(tmp_path, "DACERF-Multilane-v0", "td3", 0)
    env = gym.make("DACERF-Multilane-v0", config=SHORT)
    learning_curves.save_checkpoint(TD3("MlpPolicy", env, buffer_size=100, policy_kwargs=dict(net_arch=[8])), td3, [], 0.0)
    with pytest.raises(SystemExit, match=r"is a td3 run: evaluate_driving.py loads dacerf, dacer, dsac and sac models only"):
        export.main([str(td3), str(tmp_path / "model")])
    with pytest.raises(SystemExit):  # argparse: an algorithm it does not know
        export.main([str(td3), str(tmp_path / "model"), "--algo", "td3"])


def test_render_a_trained_driver(exported, tmp_path, capsys):
    from PIL import Image

    render = load_example("render_driving")
    out = str(tmp_path / "frames")
    [result] = render.main(["--model", exported, "--out-dir", out, "--frames", "3", "--seed", "10001"])
    printed = capsys.readouterr().out
    assert "DACERF from" in printed and "observations normalised with" in printed
    assert f"DACERF-Multilane-v0: seed 10001, {result['steps']} steps, {result['outcome']}" in printed
    assert result["strip"] == os.path.join(out, "driver.png") and result["gif"].endswith("driver.gif")
    with Image.open(result["gif"]) as gif:
        assert gif.n_frames == result["gif_frames"] > 1 and gif.size == (600, 150)
    strip = np.asarray(Image.open(result["strip"]).convert("RGB"))
    assert strip.shape == (150, 3 * 600, 3)
    # the overlays: the reference path and, in the last frame, the path driven so far
    colors = {tuple(c) for c in strip.reshape(-1, 3)}
    assert render.REFERENCE_COLOR in colors and render.TRACE_COLOR in colors
    # the same episode as evaluate_driving.py's with that seed
    evaluate = load_example("evaluate_driving")
    results = evaluate.main([exported, "--episodes", "1", "--seed", "10001"])
    assert results["episode_length"] == result["steps"]
    assert (result["outcome"] == "arrival") == bool(results["arrival_rate"])
    assert ("collision" in result["outcome"]) == bool(results["collision_rate"])
    assert ("off-road" in result["outcome"]) == bool(results["off_road_rate"])
    # without overlays: highway-env's frames as they are
    [plain] = render.main(["--model", exported, "--out-dir", out, "--frames", "2", "--seed", "10001", "--no-overlays"])
    strip = np.asarray(Image.open(plain["strip"]).convert("RGB"))
    assert strip.shape == (150, 2 * 600, 3) and render.TRACE_COLOR not in {tuple(c) for c in strip.reshape(-1, 3)}


def test_render_errors_name_the_problem(tmp_path, capsys):
    render = load_example("render_driving")
    with pytest.raises(SystemExit, match=r"no model file .*missing.zip"):
        render.main(["--model", str(tmp_path / "missing"), "--out-dir", str(tmp_path)])
    with pytest.raises(SystemExit):
        render.main(["--algo", "sac", "--out-dir", str(tmp_path)])
    assert "--algo and --config apply to --model" in capsys.readouterr().err


def test_standing_value_compares_standing_with_the_scripted_driver(capsys):
    standing_value = load_example("standing_value", BENCHMARKS)
    summary = standing_value.main(["--episodes", "3", "--stand-steps", "30", "--config", '{"routes": ["right"]}'])
    assert list(summary) == [("normal", "right")]
    # standing costs speed tracking at every step; the scripted driver's right turns are cheap
    assert summary["normal", "right"]["standing"] < -100 < summary["normal", "right"]["driving"]
    assert "| normal | right | 3 |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        standing_value.main(["--gamma", "1"])


def test_export_leaves_out_the_evaluation_config(tmp_path, capsys):
    """A run trained with starts from the traffic flow exports metadata without the key evaluations set."""
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    export = load_example("export_driver", BENCHMARKS)
    config = {**SHORT, "reference_start_probability": 0.5}
    venv = DummyVecEnv([lambda: gym.make("DACERF-Intersection-v0", config=config)])
    env_id, env_kwargs = export.checkpoint_environment(tmp_path, {"venv": venv}, None, None)
    assert env_id == "DACERF-Intersection-v0" and env_kwargs["config"] == SHORT
    assert "config key(s) ['reference_start_probability'] are left out of the exported metadata (evaluations set them)" in (
        capsys.readouterr().out
    )


@pytest.mark.parametrize("algo", ["dacerf", "dacer", "dsac", "sac"])
def test_paper_settings_carry_the_papers_data_regime_over_all_envs(algo):
    """--paper: the paper's 200 transitions per gradient step, counted over all --n-envs envs; --steps-per-gradient wins."""
    train = load_example("train_driving")
    parser = train.build_parser()
    for n_envs, train_freq in [(1, 200), (4, 50)]:
        kwargs = train.algorithm_kwargs(parser.parse_args(["--algo", algo, "--paper", "--n-envs", str(n_envs)]))
        assert (kwargs["train_freq"], kwargs["gradient_steps"], kwargs["batch_size"]) == (train_freq, 1, 512)
    assert ("flow_matching_weights" in kwargs) == (algo == "dacerf")
    kwargs = train.algorithm_kwargs(parser.parse_args(["--algo", algo, "--paper", "--steps-per-gradient", "8"]))
    assert (kwargs["train_freq"], kwargs["gradient_steps"]) == (8, 1)


@pytest.mark.parametrize("algo", ["dacerf", "dacer", "dsac", "sac"])
def test_without_options_every_learner_trains_with_its_constructor_defaults(algo):
    """As the driving results ran them (and the RL Zoo driving entries): nothing beyond the data regime asked for."""
    train = load_example("train_driving")
    parser = train.build_parser()
    assert train.algorithm_kwargs(parser.parse_args(["--algo", algo])) == {}
    kwargs = train.algorithm_kwargs(parser.parse_args(["--algo", algo, "--steps-per-gradient", "16"]))
    assert kwargs == {"train_freq": 16, "gradient_steps": 1}


@pytest.mark.parametrize("algo", ["dacer", "dsac"])
def test_dacer_and_dsac_drivers_train_export_and_evaluate_deterministically(algo, tmp_path, capsys):
    """
    A DACER or DSAC driver, trained by train_driving.py --save and as a learning_curves checkpoint exported by
    export_driver.py, loads with its own class and drives with deterministic actions, as DACERF and SAC drivers do.
    """
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    torch.set_num_threads(1)
    train = load_example("train_driving")
    evaluate = load_example("evaluate_driving")
    export = load_example("export_driver", BENCHMARKS)
    learning_curves = load_example("learning_curves", BENCHMARKS)
    algo_class, name = evaluate.ALGORITHMS[algo], algo.upper()

    # train_driving.py --algo X --save
    save = str(tmp_path / algo)
    args = ["--env", "multilane", "--algo", algo, "--timesteps", "40", "--learning-starts", "20", "--batch-size", "16"]
    train.main([*args, "--config", json.dumps(SHORT), "--vec-normalize", "--save", save, "--eval-episodes", "1"])
    assert f"DACERF-Multilane-v0 (normal), {algo}, training 40 steps" in capsys.readouterr().out
    trained = save + "_multilane"
    with open(trained + ".json") as file:
        assert json.load(file)["algo"] == algo
    results = evaluate.main([trained, "--episodes", "1"])
    assert f"{name} from {trained}.zip, observations normalised" in capsys.readouterr().out
    assert np.isfinite(results["tar"])
    driver = evaluate.load_driver(trained)
    assert type(driver.model) is algo_class
    obs, _ = driver.env.reset(seed=10_000)
    action = driver.act(obs)
    np.testing.assert_array_equal(driver.act(obs), action)  # deterministic: the same action every time
    expected = driver.model.predict(driver.vec_normalize.normalize_obs(obs), deterministic=True)[0]
    np.testing.assert_array_equal(action, expected)
    assert not np.array_equal(driver.model.predict(driver.vec_normalize.normalize_obs(obs), deterministic=False)[0], action)

    # another algorithm's class is refused with the file's policy named
    with pytest.raises(
        SystemExit,
        match=rf"cannot load .* as SAC \(.* holds a {name} model .*not a SAC model.*\): check --algo \(dacerf, dacer",
    ):
        evaluate.main([trained, "--algo", "sac"])
    other = "dsac" if algo == "dacer" else "dacer"
    with pytest.raises(SystemExit, match=rf"cannot load .* as {other.upper()} .*holds a {algo.upper()} model"):
        evaluate.main([trained, "--algo", other])
    # without metadata, the algorithm is read from the saved policy
    os.remove(trained + ".json")
    assert type(evaluate.load_driver(trained, scenario="multilane").model) is algo_class

    # a learning_curves checkpoint of the variant of that name, exported and evaluated
    env = VecNormalize(DummyVecEnv([lambda: gym.make("DACERF-Multilane-v0", config=SHORT)]), norm_reward=False)
    model = algo_class("MlpPolicy", env, learning_starts=20, batch_size=16, buffer_size=1_000, seed=0)
    model.learn(40)
    folder = learning_curves.checkpoint_dir(tmp_path / "results", "DACERF-Multilane-v0", algo, 0)
    learning_curves.save_checkpoint(model, folder, [], 1.0)
    stem = str(tmp_path / f"{algo}_multilane")
    export.main([str(folder), stem])
    assert f"{name} at 40 steps from {folder}" in capsys.readouterr().out
    with open(stem + ".json") as file:
        assert json.load(file) == {"env_id": "DACERF-Multilane-v0", "density": "normal", "config": SHORT, "algo": algo}
    driver = evaluate.load_driver(stem)
    assert type(driver.model) is algo_class and not driver.vec_normalize.training
    env.training = False
    observations = np.random.default_rng(0).normal(size=(4, *model.observation_space.shape)).astype(np.float32)
    np.testing.assert_allclose(
        np.stack([driver.act(o) for o in observations]),
        model.predict(env.normalize_obs(observations), deterministic=True)[0],
        rtol=0,
        atol=1e-6,
    )
    results = evaluate.main([stem, "--episodes", "1"])
    assert f"{name} from {stem}.zip" in capsys.readouterr().out and np.isfinite(results["tar"])


def test_an_unknown_algorithm_is_refused_with_the_known_ones(trained, tmp_path, capsys):
    evaluate = load_example("evaluate_driving")
    train = load_example("train_driving")
    render = load_example("render_driving")
    known = "dacerf, dacer, dsac and sac"
    # in the metadata beside a model
    for suffix in (".zip", "_vecnormalize.json"):
        with open(trained + suffix, "rb") as source, open(str(tmp_path / "driver") + suffix, "wb") as copy:
            copy.write(source.read())
    with open(tmp_path / "driver.json", "w") as file:
        json.dump({"env_id": "DACERF-Multilane-v0", "density": "normal", "config": SHORT, "algo": "td3"}, file)
    with pytest.raises(
        SystemExit, match=rf"'td3' \(from '.*driver.json'\) is not an algorithm the driving examples load: they load {known}"
    ):
        evaluate.main([str(tmp_path / "driver"), "--episodes", "1"])
    with pytest.raises(SystemExit, match=r"'ppo' \(from --algo\) is not an algorithm"):
        evaluate.load_algorithm("ppo")
    # on the command line: argparse names the choices
    for main, args in (
        (evaluate.main, [trained, "--algo", "td3"]),
        (train.main, ["--algo", "td3"]),
        (render.main, ["--model", trained, "--algo", "td3"]),
    ):
        with pytest.raises(SystemExit):
            main(args)
        err = capsys.readouterr().err
        assert "--algo: invalid choice: 'td3'" in err and all(name in err for name in ("dacerf", "dacer", "dsac", "sac"))
