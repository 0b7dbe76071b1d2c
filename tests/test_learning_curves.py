"""benchmarks/learning_curves.py: a run stopped and resumed from its checkpoint gives the evaluations of an uninterrupted run."""

import importlib.util
import re
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # the benchmark script, run end to end on short budgets

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def learning_curves():
    spec = importlib.util.spec_from_file_location("learning_curves", BENCHMARKS / "learning_curves.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["learning_curves"] = module
    spec.loader.exec_module(module)
    return module


def job(out: Path, variant: str, timesteps: int, **overrides) -> dict:
    settings = dict(
        env="Pendulum-v1",
        variant=variant,
        seed=3,
        timesteps=timesteps,
        eval_freq=100,
        eval_episodes=1,
        device="cpu",
        out=str(out),
        env_kwargs={},
        checkpoint_freq=100,
        learning_starts=50,
        vec_normalize=False,
        commit="abc1234",
    )
    return {**settings, **overrides}


@pytest.mark.parametrize("variant", ["dacerf", "sac"])
def test_resumed_run_matches_uninterrupted_run(tmp_path, learning_curves, variant):
    straight = learning_curves.run_one(job(tmp_path / "straight", variant, 300))
    # A run that stops at 200 steps (checkpointed at 100 and at its end), then is asked for 300: it resumes from 200
    first = learning_curves.run_one(job(tmp_path / "resumed", variant, 200))
    folder = learning_curves.checkpoint_dir(tmp_path / "resumed", "Pendulum-v1", variant, 3)
    assert (folder / "state.pkl").exists() and (folder / "replay_buffer.npz").exists()
    # The checkpoint of a finished run holds the finished model, the one its last evaluation describes
    algorithm = learning_curves.algorithm_class(learning_curves.VARIANTS[variant][0])
    assert learning_curves.load_checkpoint(algorithm, folder, "cpu")[0].num_timesteps == 200
    resumed = learning_curves.run_one(job(tmp_path / "resumed", variant, 300))
    returns = [row["mean_return"] for row in straight]
    assert [row["timesteps"] for row in resumed] == [100, 200, 300]
    assert [row["mean_return"] for row in resumed] == returns
    assert [row["mean_return"] for row in first] == returns[:2]
    # A finished run is read back, not trained again
    again = learning_curves.run_one(job(tmp_path / "resumed", variant, 300))
    assert [row["mean_return"] for row in again] == returns


@pytest.mark.parametrize("left", ["old", "tmp"])
def test_a_kill_between_the_renames_loses_no_checkpoint(tmp_path, learning_curves, left):
    straight = learning_curves.run_one(job(tmp_path / "straight", "sac", 300))
    assert {row["commit"] for row in straight} == {"abc1234"}
    learning_curves.run_one(job(tmp_path / "resumed", "sac", 200))
    folder = learning_curves.checkpoint_dir(tmp_path / "resumed", "Pendulum-v1", "sac", 3)
    # save_checkpoint renames the checkpoint to .old, then the new one from .tmp: a kill in between leaves either
    folder.rename(folder.with_name(f"{folder.name}.{left}"))
    resumed = learning_curves.run_one(job(tmp_path / "resumed", "sac", 300))
    assert [row["timesteps"] for row in resumed] == [100, 200, 300]
    assert [row["mean_return"] for row in resumed] == [row["mean_return"] for row in straight]


@pytest.mark.parametrize("normalize_reward", [False, True])
def test_vec_normalize_statistics_travel_with_the_checkpoint(tmp_path, learning_curves, normalize_reward):
    settings = dict(vec_normalize=True, normalize_reward=normalize_reward)
    straight = learning_curves.run_one(job(tmp_path / "straight", "sac", 300, **settings))
    learning_curves.run_one(job(tmp_path / "resumed", "sac", 200, **settings))
    resumed = learning_curves.run_one(job(tmp_path / "resumed", "sac", 300, **settings))
    assert [row["mean_return"] for row in resumed] == [row["mean_return"] for row in straight]
    folder = learning_curves.checkpoint_dir(tmp_path / "resumed", "Pendulum-v1", "sac", 3)
    model, *_ = learning_curves.load_checkpoint(learning_curves.algorithm_class("SAC"), folder, "cpu")
    assert model.get_vec_normalize_env().norm_reward is normalize_reward
    # evaluations report raw returns (Pendulum: between -16.3 and 0 per step, 200 steps)
    assert all(-3300 < row["mean_return"] <= 0 for row in resumed)


def test_training_env_kwargs_apply_to_training_only(tmp_path, learning_curves):
    """--train-env-kwargs: merged over --env-kwargs, config key by config key, in the training env only."""
    from stable_baselines3 import SAC

    shared = {"config": {"duration": 10}, "density": "sparse"}
    training = {"config": {"reference_start_probability": 0.0}}
    assert learning_curves.training_env_kwargs(shared, training) == {
        "config": {"duration": 10, "reference_start_probability": 0.0},
        "density": "sparse",
    }
    assert learning_curves.training_env_kwargs(shared, {}) == shared
    for train_env_kwargs, probability in (({}, 0.5), (training, 0.0)):  # the default: starts from the traffic flow
        settings = job(tmp_path, "sac", 100, env="DACERF-Intersection-v0", env_kwargs=shared, train_env_kwargs=train_env_kwargs)
        config = learning_curves.new_model(settings, SAC, {}).get_env().envs[0].unwrapped.config
        assert config["duration"] == 10 and config["reference_start_probability"] == probability


def test_evaluations_run_under_the_evaluation_config(learning_curves):
    """The evaluation env: the intersection's standard starts under --env-kwargs, which may still set them."""
    shared = {"config": {"duration": 10}, "density": "sparse"}
    assert learning_curves.evaluation_env_kwargs("DACERF-Intersection-v0", shared) == {
        "config": {"reference_start_probability": 0.0, "duration": 10},
        "density": "sparse",
    }
    explicit = {"config": {"reference_start_probability": 0.5}}
    assert learning_curves.evaluation_env_kwargs("DACERF-Intersection-v0", explicit) == explicit
    assert learning_curves.evaluation_env_kwargs("DACERF-Multilane-v0", shared) == shared
    assert learning_curves.evaluation_env_kwargs("Pendulum-v1", {}) == {}  # no config keyword for other envs


def test_several_training_envs_share_each_gradient_step(tmp_path, learning_curves):
    """--n-envs 2: two transitions per rollout step and one gradient step after it; resuming gives the same run."""
    from stable_baselines3 import SAC

    settings = dict(n_envs=2, learning_starts=100)
    straight = learning_curves.run_one(job(tmp_path / "straight", "sac", 300, **settings))
    assert [row["timesteps"] for row in straight] == [100, 200, 300]
    folder = learning_curves.checkpoint_dir(tmp_path / "straight", "Pendulum-v1", "sac", 3)
    model, *_ = learning_curves.load_checkpoint(SAC, folder, "cpu")
    assert model.get_env().num_envs == 2 and model.replay_buffer.n_envs == 2
    # 300 transitions, 100 of them before learning starts: (300 - 100) / 2 rollout steps of one gradient step each
    assert model.num_timesteps == 300 and model._n_updates == 100
    learning_curves.run_one(job(tmp_path / "resumed", "sac", 200, **settings))
    resumed = learning_curves.run_one(job(tmp_path / "resumed", "sac", 300, **settings))
    assert [row["mean_return"] for row in resumed] == [row["mean_return"] for row in straight]


def test_n_envs_must_divide_the_evaluation_and_checkpoint_frequencies(tmp_path, learning_curves, monkeypatch, capsys):
    argv = ["learning_curves.py", "--n-envs", "3", "--eval-freq", "1000", "--out", str(tmp_path)]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit):
        learning_curves.main()
    assert "--eval-freq 1000, --checkpoint-freq 5000 not a multiple of --n-envs 3" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # refused before anything is written


def test_masked_normalisation_and_drawn_densities_in_a_driving_run(tmp_path, learning_curves, monkeypatch, capsys):
    """--vec-normalize masked with --env-kwargs '{"density": "random"}': the checkpoint keeps MaskedVecNormalize."""
    from stable_baselines3 import SAC

    from sb3_dacerf.common.vec_normalize import MaskedVecNormalize

    settings = dict(
        env="DACERF-Multilane-v0", env_kwargs={"density": "random", "config": {"duration": 2}}, vec_normalize="masked"
    )
    rows = learning_curves.run_one(job(tmp_path, "sac", 100, **settings))
    assert [row["timesteps"] for row in rows] == [100]
    folder = learning_curves.checkpoint_dir(tmp_path, "DACERF-Multilane-v0", "sac", 3)
    model, *_ = learning_curves.load_checkpoint(SAC, folder, "cpu")
    normalizer = model.get_vec_normalize_env()
    assert isinstance(normalizer, MaskedVecNormalize) and normalizer.rows == (45, 8, 6)
    assert normalizer.obs_rms.row_rms.count > 100  # present vehicle rows were counted
    # Refused outside the driving scenarios, before anything is written
    monkeypatch.setattr(sys, "argv", ["learning_curves.py", "--vec-normalize", "masked", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit):
        learning_curves.main()
    assert "--vec-normalize masked normalises the vehicle rows of a driving scenario" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_steps_per_gradient_sets_the_data_regime_and_both_axes(tmp_path, learning_curves, capsys):
    """--steps-per-gradient 4 with --n-envs 2: two steps of both envs per gradient step; rows carry both axes."""
    from stable_baselines3 import SAC

    settings = dict(n_envs=2, steps_per_gradient="4", learning_starts=50, eval_freq=100, checkpoint_freq=100)
    rows = learning_curves.run_one(job(tmp_path, "sac", 200, **settings))
    # rollouts of 4 transitions; the first gradient step follows the one ending at 52 (> learning_starts), and an
    # evaluation at 100 or 200 comes before that rollout's own gradient step
    assert [row["env_steps"] for row in rows] == [row["timesteps"] for row in rows] == [100, 200]
    assert [row["gradient_steps"] for row in rows] == [(96 - 52) // 4 + 1, (196 - 52) // 4 + 1]
    folder = learning_curves.checkpoint_dir(tmp_path, "Pendulum-v1", "sac", 3)
    model, *_ = learning_curves.load_checkpoint(SAC, folder, "cpu")
    assert (model.train_freq.frequency, model.gradient_steps, model._n_updates) == (2, 1, 38)
    # a checkpoint of another regime is not resumed
    with pytest.raises(SystemExit, match=r"trains with .*'train_freq': 2.* asks for .*'train_freq': 4"):
        learning_curves.run_one(job(tmp_path, "sac", 300, **{**settings, "steps_per_gradient": "8"}))
    # below 1: two gradient steps per transition
    rows = learning_curves.run_one(job(tmp_path / "half", "sac", 100, steps_per_gradient="1/2", learning_starts=50))
    assert rows[-1]["gradient_steps"] == 2 * (99 - 50)

    learning_curves.report(rows, "Pendulum-v1", tmp_path, "gradient_steps")
    assert (tmp_path / "Pendulum-v1-gradient_steps.png").exists()
    old = [{k: v for k, v in row.items() if k not in ("env_steps", "gradient_steps")} for row in rows]
    table = learning_curves.report(old, "Pendulum-v1", tmp_path)  # runs without the new columns still plot
    assert "| sac | 1 | 100 | n/a |" in table
    with pytest.raises(SystemExit, match=r"runs of \['sac'\] have no gradient_steps column"):
        learning_curves.report(old, "Pendulum-v1", tmp_path, "gradient_steps")


def test_subproc_vec_env_steps_the_envs_in_other_processes(tmp_path, learning_curves):
    settings = dict(n_envs=2, vec_env="subproc", checkpoint_freq=0, steps_per_gradient="2", learning_starts=50)
    rows = learning_curves.run_one(job(tmp_path, "sac", 100, **settings))
    assert [(row["env_steps"], row["gradient_steps"]) for row in rows] == [(100, (98 - 52) // 2 + 1)]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--steps-per-gradient", "10", "--n-envs", "4"], "is not a multiple of n_envs 4"),
        (["--steps-per-gradient", "0.3"], "below 1 it must be 1/G"),
        (
            ["--steps-per-gradient", "3", "--timesteps", "1000"],
            "--timesteps 1000, --checkpoint-freq 5000 not a multiple of the 3 trans",
        ),
        (["--steps-per-gradient", "4", "--variants", "dacerf-utd2"], r"variants \['dacerf-utd2'\] set their own gradient steps"),
        (["--vec-env", "subproc", "--n-envs", "2"], "pass --checkpoint-freq 0 and --workers 1"),
    ],
)
def test_regime_options_refuse_what_does_not_fit(tmp_path, learning_curves, monkeypatch, capsys, argv, message):
    monkeypatch.setattr(sys, "argv", ["learning_curves.py", *argv, "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit):
        learning_curves.main()
    assert re.search(message, capsys.readouterr().err)
    assert not (tmp_path / "x").exists()


def test_langevin_diagnostics_of_a_checkpoint(tmp_path, learning_curves):
    """benchmarks/langevin_diagnostics.py: its Langevin loop is the model's, and it reads a run's checkpoint."""
    import subprocess

    import torch as th

    spec = importlib.util.spec_from_file_location("langevin_diagnostics", BENCHMARKS / "langevin_diagnostics.py")
    diagnostics = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(diagnostics)
    learning_curves.run_one(job(tmp_path, "dacerf", 200))
    folder = learning_curves.checkpoint_dir(tmp_path, "Pendulum-v1", "dacerf", 3)
    model, *_ = learning_curves.load_checkpoint(learning_curves.algorithm_class("DACERF"), folder, "cpu")
    batch = model.replay_buffer.sample(64)
    th.manual_seed(1)
    parts = diagnostics.langevin_parts(model, batch.observations, batch.actions)
    th.manual_seed(1)
    assert th.equal(parts["targets"], model.langevin_targets(batch.observations, batch.actions))
    # the noise summed over the steps: N(0, 2 η α N_l) per coordinate
    expected_std = (2 * model.langevin_step_size * model.langevin_temperature * model.langevin_steps) ** 0.5
    assert 0.8 < float(parts["diffusion"].std()) / expected_std < 1.2
    assert diagnostics.episode_bounds(th.tensor([0, 1, 0, 0, 1, 0, 1, 0]).numpy(), 2) == [(2, 5), (5, 7)]

    def diagnose(checkpoint: Path, *options: str, check: bool = True) -> subprocess.CompletedProcess:
        command = [sys.executable, str(BENCHMARKS / "langevin_diagnostics.py"), str(checkpoint), *options]
        return subprocess.run(command, capture_output=True, text=True, check=check)

    printed = diagnose(folder, "--batch", "64", "--episodes", "0").stdout
    assert "at 200 steps (last evaluation" in printed and "64 transitions of the last 200" in printed
    assert re.search(r"Langevin \(20 steps of 0\.03, temperature 0\.01\): per coordinate the gradient moves \d", printed)
    assert re.search(r"actor loss \(gain weights\): kappa \d\S* \(spread of Q\(s, a_B\) \d", printed)
    ratio = re.search(r"actor gradient norm, imitation over improvement: (\S+)", printed)
    assert ratio and float(ratio.group(1)) > 0
    learning_curves.run_one(job(tmp_path, "sac", 200))
    folder = learning_curves.checkpoint_dir(tmp_path, "Pendulum-v1", "sac", 3)
    printed = diagnose(folder, "--batch", "64", "--episodes", "0").stdout
    assert "policy coordinates beyond ±0.99" in printed and "Langevin" not in printed
    missing = diagnose(tmp_path, check=False)
    assert missing.returncode != 0 and "holds no checkpoint (no state.pkl)" in missing.stderr
