"""
RL Zoo integration. The commands run as subprocesses on a tiny budget, literally (``python -m rl_zoo3.train ...``)
when ``pip install .`` installed the start-up hook, else through ``python -m sb3_dacerf.zoo train ...``.
"""

import inspect
import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml

optuna = pytest.importorskip("optuna")
pytest.importorskip("rl_zoo3")

import rl_zoo3.callbacks  # noqa: E402
import rl_zoo3.exp_manager  # noqa: E402
import rl_zoo3.hyperparams_opt  # noqa: E402
import rl_zoo3.utils  # noqa: E402

from sb3_dacerf import DACER, DACERF, DSAC  # noqa: E402
from sb3_dacerf.common.policies import BatchRenormCritic, EnsembleLayerNorm  # noqa: E402
from sb3_dacerf.dacerf import PAPER_HYPERPARAMETERS  # noqa: E402
from sb3_dacerf.envs.dmc import DMC_ENV_IDS  # noqa: E402
from sb3_dacerf.zoo import (  # noqa: E402
    HYPERPARAMS_DIR,
    choose_threads,
    convert_dacer_params,
    convert_dacerf_params,
    convert_dsac_params,
    default_config,
    masked_normalization,
    masked_rows,
    register,
    sample_dacer_params,
    sample_dacerf_params,
    sample_dsac_params,
)

ROOT = Path(__file__).resolve().parent.parent
_HOOK = sys.modules.get("sb3_dacerf_zoo_hook")
# True when the sb3_dacerf_zoo.pth of `pip install .` ran at this interpreter's start
HOOK_INSTALLED = _HOOK is not None and _HOOK.ZooFinder in sys.meta_path

DRIVING_IDS = ["DACERF-Multilane-v0", "DACERF-Intersection-v0"]
# what the driving entries set beyond the defaults: the driving results' data regime and normaliser
DRIVING_KEYS = ["train_freq", "gradient_steps", "normalize"]
MUJOCO_IDS = [
    "Ant-v5",
    "HalfCheetah-v5",
    "Hopper-v5",
    "Humanoid-v5",
    "HumanoidStandup-v5",
    "InvertedDoublePendulum-v5",
    "InvertedPendulum-v5",
    "Pusher-v5",
    "Reacher-v5",
    "Swimmer-v5",
    "Walker2d-v5",
]
# Keys RL Zoo consumes itself before building the model
ZOO_KEYS = {"n_timesteps", "policy", "noise_type", "noise_std", "n_envs", "normalize", "env_wrapper", "env_kwargs", "callback"}
# A DACERF small enough for a few hundred steps in a test
TINY_DACERF = [
    "learning_starts:50",
    "batch_size:32",
    "langevin_steps:2",
    "policy_kwargs:dict(net_arch=[32, 32], optimizer_class='RAD')",
]
# A DACER small enough for a few hundred steps in a test
TINY_DACER = ["learning_starts:50", "batch_size:32", "policy_kwargs:dict(net_arch=[32, 32], n_diffusion_steps=5)"]
# A DSAC small enough for a few hundred steps in a test
TINY_DSAC = ["learning_starts:50", "batch_size:32", "policy_kwargs:dict(net_arch=[32, 32])"]


def zoo_command(script: str, *args: str) -> tuple[list[str], dict[str, str]]:
    """
    Command line and environment that run the RL Zoo script ``rl_zoo3.<script>`` with DACERF registered, and this
    checkout's package (wherever ``pip install -e`` points).
    """
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    if HOOK_INSTALLED:
        return [sys.executable, "-m", f"rl_zoo3.{script}", *args], env
    return [sys.executable, "-m", "sb3_dacerf.zoo", script, *args], env


def zoo(script: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run an RL Zoo script in ``cwd``, check that it succeeded and return it."""
    command, env = zoo_command(script, *args)
    result = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"{' '.join(command)}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


@pytest.mark.slow  # RL Zoo in a subprocess
def test_start_up_hook_is_installed():
    if not HOOK_INSTALLED:
        message = "the RL Zoo start-up hook is not installed (`pip install .`): Zoo tests use `python -m sb3_dacerf.zoo`"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    # At start-up the hook imports nothing heavy
    code = "import sys; print([m for m in ('torch', 'numpy', 'sb3_dacerf', 'rl_zoo3') if m in sys.modules])"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_register_is_idempotent():
    for module in (rl_zoo3.utils, rl_zoo3.hyperparams_opt, rl_zoo3.exp_manager, rl_zoo3.callbacks):
        register(module)
        register(module)
    assert rl_zoo3.utils.ALGOS["dacerf"] is DACERF and rl_zoo3.utils.ALGOS["dacer"] is DACER
    assert rl_zoo3.hyperparams_opt.HYPERPARAMS_CONVERTER["dacerf"] is convert_dacerf_params
    assert rl_zoo3.hyperparams_opt.HYPERPARAMS_CONVERTER["dacer"] is convert_dacer_params
    assert rl_zoo3.utils.ALGOS["dsac"] is DSAC
    assert rl_zoo3.hyperparams_opt.HYPERPARAMS_CONVERTER["dsac"] is convert_dsac_params
    assert rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER["dsac"] is sample_dsac_params
    assert {"dacerf", "dacer"} <= set(rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER)
    assert rl_zoo3.exp_manager.ExperimentManager._sb3_dacerf_patched
    assert rl_zoo3.callbacks.ParallelTrainCallback._sb3_dacerf_patched


@pytest.fixture
def two_threads():
    """PyTorch at two threads during the test, at its number before it afterwards."""
    threads = th.get_num_threads()
    th.set_num_threads(2)
    yield
    th.set_num_threads(threads)


@pytest.mark.parametrize(
    "argv, threads",
    [
        (["--algo", "dacerf", "--env", "Pendulum-v1", "-n", "3000"], 1),
        (["--algo=dsac", "--env", "Pendulum-v1"], 1),
        (["train", "--env", "Pendulum-v1", "--algo", "dacer"], 1),  # python -m sb3_dacerf.zoo train ...
        (["--algo", "dacerf", "--num-threads", "2"], 2),  # the user's choice, which RL Zoo applies
        (["--algo", "dacerf", "--num-thr", "2"], 2),  # as abbreviated as RL Zoo's parser accepts it
        (["--algo", "dacerf", "--num-threads", "-1"], 2),  # RL Zoo's "PyTorch's default"
        (["--algo", "sac", "--env", "Pendulum-v1"], 2),  # another package's algorithm
        (["--algo"], 2),  # RL Zoo's parser reports the error
        ([], 2),
    ],
)
def test_one_thread_for_this_package_unless_the_command_line_chooses(two_threads, argv, threads):
    choose_threads(argv)
    assert th.get_num_threads() == threads


def test_registering_rl_zoo_utils_chooses_the_threads_of_the_command_line(two_threads, monkeypatch):
    # Every RL Zoo script imports rl_zoo3.utils, and the start-up hook then registers it, before parsing its arguments
    monkeypatch.setattr(sys, "argv", ["train.py", "--algo", "dacerf", "--env", "Pendulum-v1"])
    register(rl_zoo3.utils)
    assert th.get_num_threads() == 1


def test_default_config():
    assert default_config("dacerf", "Pendulum-v1") == str(HYPERPARAMS_DIR / "dacerf.yml")
    assert default_config("dacer", "Pendulum-v1") == str(HYPERPARAMS_DIR / "dacer.yml")
    assert default_config("dsac", "DMC-walker-walk-v0") == str(HYPERPARAMS_DIR / "dsac.yml")
    assert default_config("sac", "DMC-dog-run-v0") == str(HYPERPARAMS_DIR / "sac.yml")
    assert default_config("sac", "Pendulum-v1") is None
    assert default_config("ppo", "DMC-dog-run-v0") is None


DMC_SCALING_IDS = ["DMC-humanoid-stand-v0", "DMC-humanoid-walk-v0", "DMC-dog-stand-v0"]


def test_yaml_entries():
    dacerf = yaml.safe_load((HYPERPARAMS_DIR / "dacerf.yml").read_text())
    sac = yaml.safe_load((HYPERPARAMS_DIR / "sac.yml").read_text())
    assert set(["Pendulum-v1", "MountainCarContinuous-v0", *MUJOCO_IDS, *DMC_ENV_IDS, *DRIVING_IDS]) <= set(dacerf)
    assert set([*DMC_ENV_IDS, *DRIVING_IDS]) <= set(sac)
    for env_id in ["Pendulum-v1", "MountainCarContinuous-v0", *MUJOCO_IDS]:
        gym.spec(env_id)
    dacerf_args = set(inspect.signature(DACERF).parameters)
    # Every entry uses the constructor defaults; the paper's preset is the `paper` anchor, equal to PAPER_HYPERPARAMETERS
    for env_id in ["Pendulum-v1", *MUJOCO_IDS, *DMC_ENV_IDS, *DRIVING_IDS]:
        entry = dacerf[env_id]
        assert set(entry) - ZOO_KEYS <= dacerf_args, env_id
        driving_keys = set(DRIVING_KEYS) if env_id in DRIVING_IDS else set()
        regime_keys = {"train_freq", "gradient_steps"} if env_id in DMC_SCALING_IDS else set()
        assert set(entry) <= {"policy", "n_timesteps", "learning_starts"} | driving_keys | regime_keys, env_id
    # the scalability runs: every learner two environment steps per gradient step (benchmarks/results/dmc-scaling)
    for env_id in DMC_SCALING_IDS:
        assert dacerf[env_id]["train_freq"] == sac[env_id]["train_freq"] == 2, env_id
        assert dacerf[env_id]["gradient_steps"] == sac[env_id]["gradient_steps"] == 1, env_id
    # the driving entries: as the driving results ran (learning_curves.py --steps-per-gradient 16 --vec-normalize masked
    # --timesteps 1024000, the constructors' learning_starts), every learner alike
    for env_id in DRIVING_IDS:
        for entry in (dacerf[env_id], sac[env_id]):
            assert (entry["n_timesteps"], entry["learning_starts"], entry["train_freq"], entry["gradient_steps"]) == (
                1_024_000,
                100,
                16,
                1,
            )
            assert eval(entry["normalize"]) == {"norm_obs": True, "norm_reward": False, "masked": True}
    paper = dict(dacerf["paper"])
    assert paper.pop("policy") == "MlpPolicy"
    assert eval(paper.pop("policy_kwargs")) == PAPER_HYPERPARAMETERS["policy_kwargs"]
    paper.pop("buffer_size")
    assert paper == {key: value for key, value in PAPER_HYPERPARAMETERS.items() if key != "policy_kwargs"}


def test_dacer_yaml_entries():
    dacer = yaml.safe_load((HYPERPARAMS_DIR / "dacer.yml").read_text())
    dacerf = yaml.safe_load((HYPERPARAMS_DIR / "dacerf.yml").read_text())
    # The same environments, budgets and data regimes as DACERF's file, for like-for-like comparisons
    env_ids = {key for key in dacerf if key not in ("defaults", "paper", "mujoco", "dmc", "driving")}
    assert {key for key in dacer if key not in ("defaults", "mujoco", "dmc", "driving")} == env_ids
    dacer_args = set(inspect.signature(DACER).parameters)
    for env_id in env_ids:
        entry = dacer[env_id]
        assert set(entry) - ZOO_KEYS <= dacer_args, env_id
        assert entry["n_timesteps"] == dacerf[env_id]["n_timesteps"], env_id
        for key in ("learning_starts", "train_freq", "gradient_steps"):  # the data regime, as DACERF's
            assert entry.get(key) == dacerf[env_id].get(key), (env_id, key)
    # Every entry uses the constructor defaults (the driving ones with their data regime and normalised observations)
    for env_id in ["Pendulum-v1", *MUJOCO_IDS, *DMC_ENV_IDS, *DRIVING_IDS]:
        driving_keys = set(DRIVING_KEYS) if env_id in DRIVING_IDS else set()
        regime_keys = {"train_freq", "gradient_steps"} if env_id in DMC_SCALING_IDS else set()
        assert set(dacer[env_id]) <= {"policy", "n_timesteps", "learning_starts"} | driving_keys | regime_keys, env_id


def test_dsac_yaml_entries():
    dsac = yaml.safe_load((HYPERPARAMS_DIR / "dsac.yml").read_text())
    dacer = yaml.safe_load((HYPERPARAMS_DIR / "dacer.yml").read_text())
    # The same environments, budgets and settings as DACER's file (each algorithm's constructor defaults)
    assert dsac == dacer
    dsac_args = set(inspect.signature(DSAC).parameters)
    for env_id, entry in dsac.items():
        assert set(entry) - ZOO_KEYS <= dsac_args, env_id


def test_sampler_builds_dsac():
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(4):
        trial = study.ask()
        hyperparams = sample_dsac_params(trial, 1, 1, {}, policy_kwargs={"activation_fn": th.nn.ReLU})
        assert convert_dsac_params(trial.params, {"activation_fn": th.nn.ReLU}) == hyperparams
        model = DSAC("MlpPolicy", "Pendulum-v1", buffer_size=1, **hyperparams)
        assert model.log_ent_coef.exp().item() == pytest.approx(trial.params["initial_ent_coef"])
        assert model.tau_b == trial.params["tau_b"]
        assert model.actor.activation_fn is th.nn.ReLU  # the YAML entry's policy_kwargs are kept
        study.tell(trial, 0.0)


def test_sampler_builds_dacer():
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(4):
        trial = study.ask()
        hyperparams = sample_dacer_params(trial, 1, 1, {}, policy_kwargs={"activation_fn": th.nn.ReLU})
        assert convert_dacer_params(trial.params, {"activation_fn": th.nn.ReLU}) == hyperparams
        model = DACER("MlpPolicy", "Pendulum-v1", buffer_size=1, **hyperparams)
        assert (
            model.actor.n_diffusion_steps
            == hyperparams["policy_kwargs"]["n_diffusion_steps"]
            == trial.params["n_diffusion_steps"]
        )
        assert model.actor.activation_fn is th.nn.ReLU  # the YAML entry's policy_kwargs are kept
        study.tell(trial, 0.0)


def test_sampler_builds_dacerf():
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    seen = set()
    for _ in range(12):
        trial = study.ask()
        hyperparams = sample_dacerf_params(trial, 1, 1, {}, policy_kwargs={"optimizer_class": "RAD"})
        assert hyperparams["policy_kwargs"]["optimizer_class"] == "RAD"
        # --trial-id reloads a study's parameters through the converter
        assert convert_dacerf_params(trial.params, {"optimizer_class": "RAD"}) == hyperparams
        model = DACERF("MlpPolicy", "Pendulum-v1", **hyperparams)
        critics = trial.params["critics"]
        assert hyperparams["policy_kwargs"]["critic"] == critics
        assert (
            model.actor.n_sampling_steps == hyperparams["policy_kwargs"]["n_sampling_steps"] == trial.params["n_sampling_steps"]
        )
        assert any(isinstance(m, EnsembleLayerNorm) for m in model.critic.modules()) == (critics == "layer_norm")
        assert isinstance(model.critic, BatchRenormCritic) == (critics == "batch_renorm")
        assert model.ent_coef == hyperparams["ent_coef"] and hyperparams["ent_coef"] in ("auto", 0.0)
        assert model.n_steps == hyperparams["n_steps"] in (1, 3, 5)
        seen |= {("ent_coef", hyperparams["ent_coef"]), ("critics", critics)}
        study.tell(trial, 0.0)
    # both values of each switch were drawn: the sampler explores the options benchmarks/learning.md measures
    assert seen == {
        *[("ent_coef", "auto"), ("ent_coef", 0.0), ("critics", "mlp"), ("critics", "layer_norm"), ("critics", "batch_renorm")],
    }


def test_convert_dacerf_params_critics_override_yaml_refuse_unknown():
    drawn = {"batch_size_pow": 8, "net_arch": "small"}
    # the draw overrides the critics a YAML entry chose
    assert convert_dacerf_params({**drawn, "critics": "layer_norm"}, {"critic": "batch_renorm"})["policy_kwargs"] == {
        "net_arch": [64, 64],
        "critic": "layer_norm",
    }
    with pytest.raises(ValueError, match=r"Unknown critics 'crossq'.*'batch_renorm', 'layer_norm', 'mlp'"):
        convert_dacerf_params({**drawn, "critics": "crossq"})


@pytest.mark.slow  # RL Zoo in a subprocess
def test_train_enjoy_record_video_continue(tmp_path):
    # --eval-freq, --save-freq, -P, tensorboard and callbacks go through RL Zoo's ExperimentManager
    train = zoo(
        "train",
        *["--algo", "dacerf", "--env", "Pendulum-v1", "-n", "300", "--seed", "0", "--num-threads", "1"],
        *["--eval-freq", "150", "--eval-episodes", "1", "--save-freq", "150", "-P", "-tb", "tb", "-f", "logs"],
        *["-params", *TINY_DACERF, "callback:'rl_zoo3.callbacks.RawStatisticsCallback'"],
        cwd=tmp_path,
    )
    assert "dacerf.yml" in train.stdout and "rl_zoo3/hyperparams" not in train.stdout
    run = tmp_path / "logs" / "dacerf" / "Pendulum-v1_1"
    for name in ["Pendulum-v1.zip", "best_model.zip", "rl_model_150_steps.zip", "evaluations.npz"]:
        assert (run / name).is_file(), name
    config = yaml.load((run / "Pendulum-v1" / "config.yml").read_text(), Loader=yaml.UnsafeLoader)
    # the YAML entry (defaults anchor) merged with the command line's -params, which win
    assert dict(config)["policy"] == "MlpPolicy" and dict(config)["learning_starts"] == 50
    assert list((tmp_path / "tb" / "Pendulum-v1").glob("*/events.out.tfevents.*"))

    run_args = ["--algo", "dacerf", "--env", "Pendulum-v1", "-f", "logs", "--exp-id", "1"]
    enjoy = zoo("enjoy", *run_args, "-n", "50", "--no-render", cwd=tmp_path)
    assert "Pendulum-v1_1/Pendulum-v1.zip" in enjoy.stdout

    pytest.importorskip("moviepy")
    zoo("record_video", *run_args, "-n", "20", "-o", "videos", cwd=tmp_path)
    assert list((tmp_path / "videos").glob("*.mp4"))

    resumed = zoo(
        "train",
        *["--algo", "dacerf", "--env", "Pendulum-v1", "-n", "100", "--num-threads", "1", "--eval-freq", "-1", "-f", "logs"],
        *["-i", str(run / "Pendulum-v1.zip")],
        cwd=tmp_path,
    )
    assert "Loading pretrained agent" in resumed.stdout
    assert (tmp_path / "logs" / "dacerf" / "Pendulum-v1_2" / "Pendulum-v1.zip").is_file()


@pytest.mark.slow  # RL Zoo in a subprocess
@pytest.mark.parametrize(
    "algo, model_class, params, trained",
    [
        ("dacer", DACER, TINY_DACER, lambda model: model.actor.n_diffusion_steps == 5),
        ("dsac", DSAC, TINY_DSAC, lambda model: model._n_updates == 100),
    ],
)
def test_train_and_enjoy(tmp_path, algo, model_class, params, trained):
    train = zoo(
        "train",
        *["--algo", algo, "--env", "Pendulum-v1", "-n", "150", "--seed", "0", "--num-threads", "1"],
        *["--eval-freq", "100", "--eval-episodes", "1", "-f", "logs", "-params", *params],
        cwd=tmp_path,
    )
    assert f"{algo}.yml" in train.stdout and "rl_zoo3/hyperparams" not in train.stdout
    run = tmp_path / "logs" / algo / "Pendulum-v1_1"
    for name in ["Pendulum-v1.zip", "best_model.zip", "evaluations.npz"]:
        assert (run / name).is_file(), name
    model = model_class.load(run / "Pendulum-v1.zip")
    assert model.num_timesteps == 150 and trained(model)
    run_args = ["--algo", algo, "--env", "Pendulum-v1", "-f", "logs", "--exp-id", "1"]
    enjoy = zoo("enjoy", *run_args, "-n", "50", "--no-render", cwd=tmp_path)
    assert "Pendulum-v1_1/Pendulum-v1.zip" in enjoy.stdout


@pytest.mark.slow  # RL Zoo in a subprocess
def test_sac_on_dmc_reads_package_yaml(tmp_path):
    train = zoo(
        "train",
        *["--algo", "sac", "--env", "DMC-cartpole-swingup-v0", "-n", "100", "--num-threads", "1", "--eval-freq", "-1"],
        *["-f", "logs", "-params", "learning_starts:50", "batch_size:32"],
        cwd=tmp_path,
    )
    assert "sac.yml" in train.stdout and "rl_zoo3/hyperparams" not in train.stdout
    assert (tmp_path / "logs" / "sac" / "DMC-cartpole-swingup-v0_1" / "DMC-cartpole-swingup-v0.zip").is_file()


@pytest.mark.slow  # RL Zoo in a subprocess
def test_optimize_two_workers_share_one_study(tmp_path):
    storage = tmp_path / "study.log"
    command, env = zoo_command(
        "train",
        *["--algo", "dacerf", "--env", "Pendulum-v1", "-n", "60", "--num-threads", "1", "--optimize"],
        *["--storage", str(storage), "--study-name", "dacerf-test", "--n-trials", "2", "--n-evaluations", "1"],
        *["--eval-episodes", "1", "--sampler", "random", "--pruner", "none", "--no-optim-plots", "-f", "logs", "-uuid"],
        *["-params", "learning_starts:50", "policy_kwargs:dict(optimizer_class='RAD')"],
    )
    workers = [
        subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for _ in range(2)
    ]
    for worker in workers:
        output, _ = worker.communicate(timeout=300)
        assert worker.returncode == 0, output[-3000:]

    study = optuna.load_study(
        study_name="dacerf-test",
        storage=optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(storage))),
    )
    trials = study.get_trials(states=[optuna.trial.TrialState.COMPLETE])
    assert len(trials) == 4
    assert set(trials[0].params) == {
        "learning_rate",
        "batch_size_pow",
        "tau",
        "policy_delay",
        "langevin_steps",
        "langevin_step_size",
        "langevin_temperature",
        "n_sampling_steps",
        "net_arch",
        "ent_coef",
        "flow_matching_weights",
        "critics",
        "n_steps",
    }


NAN_ENV_MODULE = """
import gymnasium as gym
import numpy as np


class NanRewardPendulum(gym.Wrapper):
    def __init__(self):
        super().__init__(gym.make("Pendulum-v1"))

    def step(self, action):
        observation, _, terminated, truncated, info = self.env.step(action)
        return observation, float("nan"), terminated, truncated, info


gym.register("NanRewardPendulum-v0", entry_point=NanRewardPendulum)
"""


@pytest.mark.slow  # RL Zoo in a subprocess
def test_optimize_prunes_a_trial_whose_loss_is_not_finite_and_goes_on(tmp_path):
    # RL Zoo prunes trials that raise ValueError or AssertionError; any other error stops the whole study
    (tmp_path / "nan_env.py").write_text(NAN_ENV_MODULE)
    (tmp_path / "nan.yml").write_text("NanRewardPendulum-v0:\n  policy: MlpPolicy\n  n_timesteps: 60\n  learning_starts: 50\n")
    command, env = zoo_command(
        "train",
        *["--algo", "dacerf", "--env", "NanRewardPendulum-v0", "--gym-packages", "nan_env", "--conf-file", "nan.yml"],
        *["--num-threads", "1", "--optimize", "--n-trials", "2", "--n-evaluations", "1", "--eval-episodes", "1"],
        *["--storage", "study.log", "--study-name", "nan", "--sampler", "random", "--pruner", "none", "--no-optim-plots"],
        *["-f", "logs", "-params", "policy_kwargs:dict(optimizer_class='RAD')"],
    )
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tmp_path), env.get("PYTHONPATH")]))
    result = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    output = result.stdout + result.stderr
    assert "non-finite critic loss" in output and "the replay buffer holds non-finite rewards" in output, output[-3000:]
    # both trials ran and were pruned: the study is not stopped by the first one (RL Zoo then fails on "no best trial")
    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(tmp_path / "study.log")))
    study = optuna.load_study(study_name="nan", storage=storage)
    assert [trial.state for trial in study.trials] == [optuna.trial.TrialState.PRUNED] * 2, output[-3000:]


# A YAML entry's normalize with the masked normaliser (driving ids): the string RL Zoo evaluates, as in a YAML file
MASKED_NORMALIZE = "dict(norm_obs=True, norm_reward=False, masked=True)"


def test_masked_normalization_takes_its_key_out_and_refuses_what_it_cannot_do():
    kwargs = eval(MASKED_NORMALIZE)
    assert masked_normalization(kwargs) is True
    assert kwargs == {"norm_obs": True, "norm_reward": False}  # VecNormalize's and MaskedVecNormalize's arguments
    plain = {"norm_obs": True, "norm_reward": False}
    assert masked_normalization(plain) is False and plain == {"norm_obs": True, "norm_reward": False}
    with pytest.raises(ValueError, match="masked=1: write masked=True"):
        masked_normalization({"masked": 1})
    with pytest.raises(ValueError, match="norm_obs=False turns observation normalisation off"):
        masked_normalization({"masked": True, "norm_obs": False})


def test_masked_rows_are_the_driving_vehicle_rows_and_another_env_is_refused():
    pytest.importorskip("highway_env")
    from stable_baselines3.common.vec_env import DummyVecEnv

    from sb3_dacerf.envs.driving.common.observation import vehicle_rows

    driving = DummyVecEnv([lambda: gym.make("DACERF-Intersection-v0")])
    assert masked_rows(driving, "DACERF-Intersection-v0") == vehicle_rows(driving.get_attr("config")[0])
    with pytest.raises(ValueError, match=r"Pendulum-v1 has no driving config.*drop masked=True"):
        masked_rows(DummyVecEnv([lambda: gym.make("Pendulum-v1")]), "Pendulum-v1")


@pytest.fixture(scope="module")
def masked_driving_run(tmp_path_factory) -> Path:
    """A folder where RL Zoo trained DACERF on DACERF-Multilane-v0 for 300 steps with a YAML entry of the masked normaliser."""
    pytest.importorskip("highway_env")
    folder = tmp_path_factory.mktemp("masked")
    entry = yaml.safe_load((HYPERPARAMS_DIR / "dacerf.yml").read_text())["DACERF-Multilane-v0"]
    entry.update(normalize=MASKED_NORMALIZE, learning_starts=50, batch_size=32, langevin_steps=2)
    entry["policy_kwargs"] = "dict(net_arch=[32, 32], optimizer_class='RAD')"
    (folder / "driving.yml").write_text(yaml.safe_dump({"DACERF-Multilane-v0": entry}))
    train = zoo(
        "train",
        *["--algo", "dacerf", "--env", "DACERF-Multilane-v0", "--conf-file", "driving.yml", "-n", "300", "--seed", "0"],
        *["--eval-freq", "150", "--eval-episodes", "1", "-f", "logs"],
        cwd=folder,
    )
    assert "Normalization activated: MaskedVecNormalize" in train.stdout
    return folder


@pytest.mark.slow  # RL Zoo in a subprocess
def test_masked_normaliser_from_a_yaml_entry_trains_and_enjoys(masked_driving_run):
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from sb3_dacerf.common.vec_normalize import MaskedVecNormalize
    from sb3_dacerf.envs.driving.common.observation import vehicle_rows

    run = masked_driving_run / "logs" / "dacerf" / "DACERF-Multilane-v0_1"
    venv = DummyVecEnv([lambda: gym.make("DACERF-Multilane-v0")])
    statistics = VecNormalize.load(str(run / "DACERF-Multilane-v0" / "vecnormalize.pkl"), venv)
    assert isinstance(statistics, MaskedVecNormalize)
    assert statistics.rows == vehicle_rows(venv.get_attr("config")[0]) and not statistics.norm_reward
    # the vehicle rows' entries share the statistics of the present rows; an empty row normalises to zeros
    start, count, size = statistics.rows
    assert np.all(statistics.obs_rms.var[start : start + count * size].reshape(count, size) == statistics.obs_rms.row_rms.var)
    empty = np.zeros((1, venv.observation_space.shape[0]), dtype=np.float32)
    assert not statistics.normalize_obs(empty)[0, start : start + count * size].any()

    enjoy = zoo(
        "enjoy",
        *["--algo", "dacerf", "--env", "DACERF-Multilane-v0", "-f", "logs", "--exp-id", "1", "-n", "50", "--no-render"],
        cwd=masked_driving_run,
    )
    assert "DACERF-Multilane-v0_1/DACERF-Multilane-v0.zip" in enjoy.stdout


@pytest.mark.slow  # a subprocess
def test_model_of_the_masked_normaliser_exports_with_its_statistics(masked_driving_run):
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    run = masked_driving_run / "logs" / "dacerf" / "DACERF-Multilane-v0_1"
    model_path, statistics_path = run / "DACERF-Multilane-v0.zip", run / "DACERF-Multilane-v0" / "vecnormalize.pkl"
    command = [sys.executable, "-m", "sb3_dacerf.export", str(model_path), "--format", "torchscript", "--out", "policy.pt"]
    export = subprocess.run(
        # RL Zoo keeps the statistics as a pickle: this run's own file, read with the explicit opt-in
        [*command, "--vec-normalize", str(statistics_path), "--unsafe-run-code-from-file"],
        env=zoo_command("train")[1],  # this checkout's package
        cwd=masked_driving_run,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert export.returncode == 0, export.stderr[-3000:]

    # The exported policy on raw observations acts as the model on the observations the statistics normalise
    venv = DummyVecEnv([lambda: gym.make("DACERF-Multilane-v0", density="random")])
    statistics = VecNormalize.load(str(statistics_path), venv)
    statistics.training = False
    observations = []
    venv.seed(1)
    obs = venv.reset()
    for _ in range(50):
        observations.append(obs[0])
        obs, *_ = venv.step(np.zeros((1, 2), dtype=np.float32))
    raw = np.stack(observations)
    expected, _ = DACERF.load(model_path).predict(statistics.normalize_obs(raw), deterministic=True)
    with th.no_grad():
        exported = th.jit.load(str(masked_driving_run / "policy.pt"))(th.as_tensor(raw)).numpy()
    assert np.abs(exported - expected).max() <= 1e-5
