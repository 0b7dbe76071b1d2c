"""
RL Zoo's own tests for SAC, run with each algorithm of this package in its place: the commands of
``tests/test_train.py`` (``test_train[sac-Pendulum-v1]``, ``test_save_load_replay_buffer``, ``test_parallel_train``)
and ``tests/test_hyperparams_opt.py`` (``test_optimize[random-median-sac-Pendulum-v1]``) of RL Zoo's source
distribution, word for word but for ``sac`` and ``python train.py`` (here ``python -m rl_zoo3.train``, or
``python -m sb3_dacerf.zoo train`` without the start-up hook). ``tests/test_enjoy.py`` downloads trained agents; its
``enjoy`` and ``record_video`` commands run here on an agent trained first, as its ``test_load`` does.

PyTorch runs on one thread (``OMP_NUM_THREADS=1``), which leaves the commands unchanged.
"""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rl_zoo3")

from sb3_dacerf.zoo import ALGORITHMS

ROOT = Path(__file__).resolve().parent.parent
_HOOK = sys.modules.get("sb3_dacerf_zoo_hook")
HOOK_INSTALLED = _HOOK is not None and _HOOK.ZooFinder in sys.meta_path

pytestmark = [pytest.mark.slow, pytest.mark.parametrize("algo", sorted(ALGORITHMS))]


def run(command: str, cwd: Path) -> subprocess.CompletedProcess:
    """
    Run an RL Zoo command written as in RL Zoo's tests (``python train.py ...``, ``python -m rl_zoo3.<script> ...``),
    check that it exited with 0 and return it.
    """
    words = shlex.split(command)
    assert words[0] == "python", command
    if words[1] == "-m":
        script, args = words[2].removeprefix("rl_zoo3."), words[3:]
    else:
        script, args = words[1].removesuffix(".py"), words[2:]
    # this checkout's package, wherever `pip install -e` points
    python_path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": python_path}
    if HOOK_INSTALLED:
        program = [sys.executable, "-m", f"rl_zoo3.{script}"]
    else:
        program = [sys.executable, "-m", "sb3_dacerf.zoo", script]
    result = subprocess.run([*program, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, f"{command}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


# tests/test_train.py


def test_train(tmp_path, algo):
    N_STEPS = 100
    env_id = "Pendulum-v1"
    cmd = f"python train.py -n {N_STEPS} --algo {algo} --env {env_id} --log-folder {tmp_path} "
    run(cmd, tmp_path)
    assert (tmp_path / algo / "Pendulum-v1_1" / "Pendulum-v1.zip").is_file()


def test_save_load_replay_buffer(tmp_path, algo):
    N_STEPS = 100
    env_id = "Pendulum-v1"
    cmd = (
        f"python train.py -n {N_STEPS} --algo {algo} --env {env_id} --log-folder {tmp_path} "
        "--save-replay-buffer -params buffer_size:1000 --env-kwargs g:8.0 --eval-env-kwargs g:5.0 "
    )
    run(cmd, tmp_path)

    assert os.path.isfile(os.path.join(tmp_path, f"{algo}/Pendulum-v1_1/replay_buffer.pkl"))

    saved_model = os.path.join(tmp_path, f"{algo}/Pendulum-v1_1/Pendulum-v1.zip")
    cmd += f"-i {saved_model}"

    run(cmd, tmp_path)
    assert (tmp_path / algo / "Pendulum-v1_2" / "Pendulum-v1.zip").is_file()


def test_parallel_train(tmp_path, algo):
    cmd = (
        f"python train.py -n 1000 --algo {algo} --env Pendulum-v1 --log-folder {tmp_path} "
        # Test custom argument for the monitor too
        "-params monitor_kwargs:'dict(info_keywords=(\"TimeLimit.truncated\",))' "
        "callback:\"'rl_zoo3.callbacks.ParallelTrainCallback'\""
    )
    run(cmd, tmp_path)
    # Beyond RL Zoo's test: the thread took gradient steps (learning_starts is 1000 in the YAML files: one round of
    # ParallelTrainCallback's 100 steps, started at the last step), and the saved model is the trained one
    model = ALGORITHMS[algo].load(tmp_path / algo / "Pendulum-v1_1" / "Pendulum-v1.zip")
    assert model.num_timesteps == 1000 and model._n_updates == 100
    action, _ = model.predict(np.array([1.0, 0.0, 0.0], dtype=np.float32))
    assert action.shape == (1,) and -2.0 <= action[0] <= 2.0


# tests/test_hyperparams_opt.py, test_optimize[random-median-sac-Pendulum-v1]


def test_optimize(tmp_path, algo):
    N_STEPS, N_TRIALS, N_JOBS = 100, 2, 1
    env_id, sampler, pruner = "Pendulum-v1", "random", "median"
    maybe_params = ""
    cmd = (
        f"python train.py -n {N_STEPS} --algo {algo} --env {env_id} --log-folder {tmp_path} "
        f"-params policy_kwargs:'dict(net_arch=[32])' {maybe_params} "
        f"--no-optim-plots --seed 14 --n-trials {N_TRIALS} --n-jobs {N_JOBS} "
        f"--sampler {sampler} --pruner {pruner} --n-evaluations 2 --n-startup-trials 1 -optimize"
    )
    result = run(cmd, tmp_path)
    assert re.search(rf"Number of finished trials:\s+{N_TRIALS}\n", result.stdout), result.stdout[-3000:]


# tests/test_enjoy.py: test_trained_agents' and test_load's enjoy commands, test_record_video


def test_enjoy_and_record_video(tmp_path, algo):
    N_STEPS = 100
    env_id = "Pendulum-v1"
    # test_load's training command (its -c tests/test_config.yml and n_envs are A2C's), which saves a best model
    # and checkpoints
    run(f"python train.py --algo {algo} --env {env_id} -n 1000 -f {tmp_path} --eval-freq 500 --save-freq 500 -P", tmp_path)

    # test_trained_agents
    run(f"python enjoy.py --algo {algo} --env {env_id} -n {N_STEPS} -f {tmp_path} --no-render", tmp_path)
    # test_load
    base_cmd = f"python enjoy.py --algo {algo} --env {env_id} -n {N_STEPS} -f {tmp_path} --no-render "
    run(base_cmd + "--load-best -P", tmp_path)
    run(base_cmd + "--load-checkpoint 500", tmp_path)
    run(base_cmd + "--load-last-checkpoint", tmp_path)

    # test_record_video, with -f for the agent trained above instead of the downloaded one
    pytest.importorskip("moviepy")
    videos = tmp_path / "videos"
    run(f"python -m rl_zoo3.record_video -n 100 --algo {algo} --env {env_id} -f {tmp_path} -o {videos}", tmp_path)
    video_path = str(videos / f"final-model-{algo}-Pendulum-v1-step-0-to-step-100.mp4")
    # File is not empty
    assert os.stat(video_path).st_size != 0, "Recorded video is empty"
