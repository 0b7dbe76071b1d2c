"""
Learning curves at equal environment steps: DACER-F against SAC (and variants), several seeds.

Each run trains one (variant, seed) pair and evaluates the deterministic policy every ``--eval-freq`` steps on a
separate environment. Runs are spread over ``--workers`` processes (one torch thread each). Results go to
``<out>/<env>.csv`` (one row per evaluation) and ``<out>/<env>.png`` (mean and 95% bootstrap interval over seeds);
a markdown table of the final evaluations is printed.

Every run also keeps its own evaluations in ``<out>/runs/<env>/<variant>-seed<k>.csv``, rewritten after each
evaluation: a finished run (last row at ``--timesteps``) is not trained again when the command is repeated, so long
comparisons can be run in pieces (one variant or seed range at a time) and ``--report-only`` plots what is there.

    python benchmarks/learning_curves.py --quick                       # Pendulum, 2 seeds, 3k steps, < 5 min
    python benchmarks/learning_curves.py --env Pendulum-v1 --timesteps 20000 --seeds 3 --variants dacerf sac
    python benchmarks/learning_curves.py --env DACERF-Intersection-v0 --variants dacerf sac --timesteps 50000

Environment ids registered by ``sb3_dacerf`` (driving, DMC) work too; for environments whose ``info`` carries
``is_success`` / ``collision`` / ``off_road`` the arrival, collision and off-road rates of the evaluation
episodes are reported as well. ``--env-kwargs`` go to ``gym.make`` of every env, ``--train-env-kwargs`` to the
training env's only. Evaluations run under the env's evaluation config, which ``--env-kwargs`` may override: at the
intersection from the standard starts (``reference_start_probability`` 0), while training keeps the default 0.5.
``--env-kwargs '{"density": "random"}'`` draws each driving episode's traffic density (training and evaluations),
``--train-env-kwargs`` the training episodes' only; ``--vec-normalize masked`` normalises the observations with
:class:`sb3_dacerf.common.vec_normalize.MaskedVecNormalize`, whose empty vehicle rows stay zeros at any density.

``--n-envs N`` trains on N copies of the environment stepped together (SB3's ``DummyVecEnv``, in the same process):
each rollout step collects N transitions and is followed by the variant's gradient steps (one by default), so a run
of ``--timesteps`` transitions takes ``--timesteps / N`` gradient steps, N transitions per gradient step; steps,
evaluations and checkpoints are counted in transitions.

``--steps-per-gradient S`` sets the data regime instead: S environment steps (transitions) per gradient step, the
DACER-F paper's "sample batch size" (200 in its table; see the "Data regime" guide and
``sb3_dacerf.common.regime``). With ``--n-envs N``, S >= 1 must be a multiple of N: each rollout steps the N
environments S / N times, then makes one gradient step; S < 1 must be 1/G (``1/4``, ``0.25``): G gradient steps per
transition. ``--vec-env subproc`` steps the N environments in as many processes (SB3's ``SubprocVecEnv``; count the
cores); its environments cannot be pickled into a checkpoint, so it needs ``--checkpoint-freq 0``. Every row of the
CSVs carries both axes, ``env_steps`` (= ``timesteps``, transitions) and ``gradient_steps`` (updates made);
``--x-axis gradient_steps`` plots against the latter.
"""

import argparse
import json
import multiprocessing as mp
import signal
import sys
import time
from pathlib import Path
from typing import Any

import _checkout  # the repository's sb3_dacerf, not an installed copy; its ROOT names the commit
import numpy as np

sys.path.append(str(_checkout.ROOT / "examples"))  # evaluate_driving's evaluation_config

VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    # name: (algorithm, constructor kwargs); "action_noise_std" becomes a NormalActionNoise
    "dacerf": ("DACERF", {}),
    # the paper's own settings (sb3_dacerf.dacerf.PAPER_HYPERPARAMETERS)
    "dacerf-paper": ("DACERF", dict(paper=True)),
    # ablations of the defaults, one change each
    "dacerf-noreg": ("DACERF", dict(ent_coef=0.0)),
    "dacerf-alpha1": ("DACERF", dict(ent_coef="auto_1")),
    "dacerf-ln": ("DACERF", dict(policy_kwargs=dict(critic="layer_norm"))),  # = the defaults (named so in earlier results)
    "dacerf-mlp": ("DACERF", dict(policy_kwargs=dict(critic="mlp"))),  # SB3's MLP critics
    # DSAC-T's Gaussian critics and their loss (the official DACER's critics)
    "dacerf-dist": ("DACERF", dict(policy_kwargs=dict(distributional_critic=True))),
    # CrossQ's learning rate 1e-3 and Adam betas (0.5, 0.999), with the default critics and their targets
    "dacerf-lr": ("DACERF", dict(learning_rate=1e-3, policy_kwargs=dict(optimizer_kwargs=dict(betas=(0.5, 0.999))))),
    # CrossQ's critics: batch renormalisation, no target networks (same width, learning rate and Adam as the defaults)
    "dacerf-crossq": ("DACERF", dict(policy_kwargs=dict(critic="batch_renorm"))),
    # ... with CrossQ's learning rate 1e-3 and Adam betas (0.5, 0.999) for the actor and the critics
    "dacerf-crossq-lr": (
        "DACERF",
        dict(
            learning_rate=1e-3,
            policy_kwargs=dict(critic="batch_renorm", optimizer_kwargs=dict(betas=(0.5, 0.999))),
        ),
    ),
    "dacerf-delay1": ("DACERF", dict(policy_delay=1)),
    "dacerf-steps3": ("DACERF", dict(policy_kwargs=dict(n_sampling_steps=3))),
    # fewer, larger Langevin steps with the same total drift and noise (N_l * eta = 0.6, N_l * eta * alpha fixed)
    "dacerf-langevin5": ("DACERF", dict(langevin_steps=5, langevin_step_size=0.12)),
    "dacerf-langevin10": ("DACERF", dict(langevin_steps=10, langevin_step_size=0.06)),
    # the actor's clamp to [-1, 1] with the identity's gradient (straight-through) instead of a zero gradient in
    # saturated coordinates; a measurement, not an option of the package (see straight_through_policy)
    "dacerf-straight-through": ("DACERF", dict(policy="straight-through")),
    "dacerf-nstep3": ("DACERF", dict(n_steps=3)),  # 3-step returns in the critic targets (SB3's NStepReplayBuffer)
    "dacerf-utd2": ("DACERF", dict(gradient_steps=2)),  # two gradient steps per environment step (twice the updates)
    "dacerf-tau001": ("DACERF", dict(tau=0.001)),
    "dacerf-noise": ("DACERF", dict(ent_coef=0.0, action_noise_std=0.1)),
    "dacer": ("DACER", {}),
    "dsac": ("DSAC", {}),  # DSAC-T with the authors' defaults (sb3_dacerf.DSAC)
    "sac": ("SAC", {}),
    "sac-nstep3": ("SAC", dict(n_steps=3)),
    # a discount whose horizon 1 / (1 - gamma) = 500 steps covers a 400-step intersection episode (the driving
    # rewards are audited as undiscounted episode totals)
    "sac-gamma998": ("SAC", dict(gamma=0.998)),
    "td3": ("TD3", dict(action_noise_std=0.1)),  # RL Zoo's exploration noise for TD3 on MuJoCo tasks
    "tqc": ("TQC", {}),
    "crossq": ("CrossQ", {}),
}


def checkout_commit() -> str:
    """The commit of the code that trains (``<hash>+dirty`` when the checkout has uncommitted changes), for the run files."""
    import subprocess

    def git(*arguments: str) -> str:
        return subprocess.run(["git", *arguments], cwd=_checkout.ROOT, capture_output=True, text=True).stdout.strip()

    dirty = git("status", "--porcelain", "--untracked-files=no", "--", "sb3_dacerf", "benchmarks/learning_curves.py")
    return (git("rev-parse", "--short", "HEAD") or "unknown") + ("+dirty" if dirty else "")


def algorithm_class(name: str) -> type:
    import sb3_dacerf

    if name in ("SAC", "TD3"):
        import stable_baselines3

        return getattr(stable_baselines3, name)
    if name in ("TQC", "CrossQ"):
        import sb3_contrib

        return getattr(sb3_contrib, name)
    return getattr(sb3_dacerf, name)


def straight_through_policy() -> type:
    """DACERFPolicy whose actor clamps its actions to [-1, 1] straight-through: forward a clamp, backward the identity."""
    from sb3_dacerf.dacerf.policies import DACERFPolicy, FlowActor

    class StraightThroughFlowActor(FlowActor):
        def squash(self, actions: Any) -> Any:
            return actions + (actions.clamp(-1.0, 1.0) - actions).detach()

    class StraightThroughDACERFPolicy(DACERFPolicy):
        actor_class = StraightThroughFlowActor

    return StraightThroughDACERFPolicy


POLICIES = {"straight-through": straight_through_policy}


def run_file(out: Path, env_id: str, variant: str, seed: int) -> Path:
    """Where one run keeps its evaluations."""
    return out / "runs" / env_id.replace("/", "_") / f"{variant}-seed{seed}.csv"


def checkpoint_dir(out: Path, env_id: str, variant: str, seed: int) -> Path:
    """Where one run keeps its last checkpoint (model, replay buffer, environment, random states): never committed."""
    return out / "checkpoints" / env_id.replace("/", "_") / f"{variant}-seed{seed}"


def read_rows(path: Path) -> list[dict[str, Any]]:
    import pandas as pd

    return pd.read_csv(path).to_dict("records") if path.exists() else []


BUFFER_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def save_checkpoint(model: Any, folder: Path, rows: list[dict[str, Any]], wall_seconds: float) -> None:
    """
    Everything a run needs to go on exactly as if it had not stopped: the model (with its optimizers and
    ``_last_obs``), the filled part of the replay buffer, the training environment (pickled mid-episode, with its
    random state and VecNormalize statistics), the global random states and the evaluations so far. Written to a
    temporary folder, then renamed over the previous checkpoint, so a kill while saving keeps the previous one.
    """
    import pickle
    import random
    import shutil

    import cloudpickle
    import torch as th
    from stable_baselines3.common.vec_env import VecNormalize

    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    model.save(tmp / "model.zip")
    buffer = model.replay_buffer
    size = buffer.buffer_size if buffer.full else buffer.pos
    arrays = {name: getattr(buffer, name)[:size] for name in BUFFER_ARRAYS if getattr(buffer, name, None) is not None}
    np.savez(tmp / "replay_buffer.npz", **arrays)
    env = model.get_env()
    # VecNormalize pickles its statistics without the environments it wraps: both are kept
    normalize = env if isinstance(env, VecNormalize) else None
    with open(tmp / "env.pkl", "wb") as file:
        venv = env.venv if normalize else env
        cloudpickle.dump(dict(venv=venv, normalize=normalize, returns=getattr(normalize, "returns", None)), file)
    state = dict(
        buffer_pos=buffer.pos,
        buffer_full=buffer.full,
        torch=th.get_rng_state(),
        numpy=np.random.get_state(),
        python=random.getstate(),
        action_space=model.action_space.np_random.bit_generator.state,
        rows=rows,
        wall_seconds=wall_seconds,
    )
    with open(tmp / "state.pkl", "wb") as file:
        pickle.dump(state, file)
    old = folder.with_name(folder.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if folder.exists():
        folder.rename(old)
    tmp.rename(folder)
    shutil.rmtree(old, ignore_errors=True)


def recover_checkpoint(folder: Path) -> None:
    """
    Put back the checkpoint a kill during :func:`save_checkpoint`'s renames left aside: the new one if it was written
    completely (its ``state.pkl`` is written last), otherwise the previous one.
    """
    if folder.exists():
        return
    tmp, old = folder.with_name(folder.name + ".tmp"), folder.with_name(folder.name + ".old")
    for candidate in (tmp, old):
        if (candidate / "state.pkl").exists():
            candidate.rename(folder)
            return


def load_checkpoint(algorithm: type, folder: Path, device: str) -> tuple[Any, list[dict[str, Any]], float]:
    """The model (with its environment and replay buffer), the evaluations and the training seconds of a checkpoint."""
    import pickle
    import random

    import cloudpickle
    import torch as th

    with open(folder / "env.pkl", "rb") as file:
        saved = cloudpickle.load(file)
    env = saved["venv"]
    if saved["normalize"] is not None:
        env = saved["normalize"]
        env.set_venv(saved["venv"])
        env.returns = saved["returns"]
    with open(folder / "state.pkl", "rb") as file:
        state = pickle.load(file)
    # force_reset=False: go on from the environment's state and the model's _last_obs
    model = algorithm.load(folder / "model.zip", env=env, device=device, force_reset=False)
    buffer = model.replay_buffer
    with np.load(folder / "replay_buffer.npz") as arrays:
        for name in arrays.files:
            getattr(buffer, name)[: len(arrays[name])] = arrays[name]
    buffer.pos, buffer.full = state["buffer_pos"], state["buffer_full"]
    # Loading re-seeds everything (SB3's _setup_model): put the random states back where they were
    th.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    model.action_space.np_random.bit_generator.state = state["action_space"]
    return model, state["rows"], state["wall_seconds"]


def training_env_kwargs(env_kwargs: dict[str, Any], train_env_kwargs: dict[str, Any]) -> dict[str, Any]:
    """
    The ``gym.make`` keyword arguments of the training env: ``env_kwargs`` updated by ``train_env_kwargs``, the two
    ``config`` dicts merged key by key (a training-only config key keeps the shared ones).
    """
    merged = {**env_kwargs, **train_env_kwargs}
    if "config" in env_kwargs and "config" in train_env_kwargs:
        merged["config"] = {**env_kwargs["config"], **train_env_kwargs["config"]}
    return merged


def evaluation_env_kwargs(env_id: str, env_kwargs: dict[str, Any]) -> dict[str, Any]:
    """
    The ``gym.make`` keyword arguments of the evaluation env: ``env_kwargs`` over the env's evaluation config
    (``evaluate_driving.evaluation_config``: the intersection's standard starts), ``config`` key by key.
    """
    from evaluate_driving import evaluation_config

    config = evaluation_config(env_id, config=env_kwargs.get("config"))
    return {**env_kwargs, "config": config} if config else env_kwargs


def new_model(job: dict[str, Any], algorithm: type, kwargs: dict[str, Any]) -> Any:
    """
    A fresh model of one variant on its training environment: ``job["n_envs"]`` copies (default 1) in a
    ``DummyVecEnv`` (``SubprocVecEnv`` with ``job["vec_env"] == "subproc"``), VecNormalize'd with
    ``job["vec_normalize"]`` (``True`` or ``"plain"``: SB3's; ``"masked"``:
    :class:`~sb3_dacerf.common.vec_normalize.MaskedVecNormalize` over a driving scenario's vehicle rows), rewards too
    with ``job["normalize_reward"]``; ``job["steps_per_gradient"]`` sets ``train_freq`` and ``gradient_steps``
    (``sb3_dacerf.common.regime.steps_per_gradient_kwargs``).
    """
    import gymnasium as gym
    from stable_baselines3.common.noise import NormalActionNoise
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

    from sb3_dacerf.common.regime import steps_per_gradient_kwargs

    env_kwargs = training_env_kwargs(job["env_kwargs"], job.get("train_env_kwargs") or {})
    n_envs = job.get("n_envs", 1)
    if job.get("vec_env", "dummy") == "subproc":
        # "module:id" makes the worker processes import (and so register) the package's ids
        env_id = f"sb3_dacerf:{job['env']}"
        env = SubprocVecEnv([lambda: gym.make(env_id, **env_kwargs)] * n_envs)
    else:
        env = DummyVecEnv([lambda: gym.make(job["env"], **env_kwargs)] * n_envs)
    norm_reward = bool(job.get("normalize_reward"))
    if job["vec_normalize"] == "masked":
        from sb3_dacerf.common.vec_normalize import MaskedVecNormalize
        from sb3_dacerf.envs.driving.common.observation import vehicle_rows

        env = MaskedVecNormalize(env, rows=vehicle_rows(env.get_attr("config")[0]), norm_obs=True, norm_reward=norm_reward)
    elif job["vec_normalize"] or norm_reward:
        env = VecNormalize(env, norm_obs=True, norm_reward=norm_reward)
    kwargs = dict(kwargs)
    if job.get("steps_per_gradient") is not None:
        kwargs.update(steps_per_gradient_kwargs(job["steps_per_gradient"], n_envs))
    if "action_noise_std" in kwargs:
        dim = env.action_space.shape[0]
        kwargs["action_noise"] = NormalActionNoise(np.zeros(dim), kwargs.pop("action_noise_std") * np.ones(dim))
    policy = POLICIES[kwargs.pop("policy")]() if "policy" in kwargs else "MlpPolicy"
    return algorithm(policy, env, seed=job["seed"], device=job["device"], **kwargs)


def check_regime(model: Any, job: dict[str, Any], folder: Path) -> None:
    """Refuse to resume a checkpoint whose data regime (``train_freq``, ``gradient_steps``) the job does not ask for."""
    if job.get("steps_per_gradient") is None:
        return
    from sb3_dacerf.common.regime import steps_per_gradient_kwargs

    wanted = steps_per_gradient_kwargs(job["steps_per_gradient"], job.get("n_envs", 1))
    saved = dict(train_freq=model.train_freq.frequency, gradient_steps=model.gradient_steps)
    if saved != wanted:
        raise SystemExit(
            f"{folder}: the checkpoint trains with {saved}, --steps-per-gradient {job['steps_per_gradient']} asks for "
            f"{wanted}: use another --out for another data regime"
        )


def paper_kwargs(job: dict[str, Any], kwargs: dict[str, Any]) -> dict[str, Any]:
    """
    ``PAPER_HYPERPARAMETERS`` updated by a variant's own ``kwargs``; without ``--steps-per-gradient``, the paper's 200
    transitions per gradient step are collected over all the ``--n-envs`` environments.
    """
    from sb3_dacerf.common.regime import steps_per_gradient_kwargs
    from sb3_dacerf.dacerf import PAPER_HYPERPARAMETERS

    kwargs = {**PAPER_HYPERPARAMETERS, **kwargs}
    if job.get("steps_per_gradient") is None:
        kwargs.update(steps_per_gradient_kwargs(PAPER_HYPERPARAMETERS["train_freq"], job.get("n_envs", 1)))
    return kwargs


def run_one(job: dict[str, Any]) -> list[dict[str, Any]]:
    """
    Train one variant with one seed; return one row per evaluation (read back if the run already finished).
    A run with a checkpoint goes on from it, with the same evaluations as an uninterrupted run.
    """
    out = Path(job["out"])
    path = run_file(out, job["env"], job["variant"], job["seed"])
    done_rows = read_rows(path)
    if done_rows and done_rows[-1]["timesteps"] >= job["timesteps"]:
        print(f"{path}: already finished, not trained again", flush=True)
        return done_rows

    import gymnasium as gym
    import pandas as pd
    import torch as th
    from stable_baselines3.common.callbacks import BaseCallback

    import sb3_dacerf  # noqa: F401  (registers the package's environment ids)

    th.set_num_threads(1)
    algorithm_name, kwargs = VARIANTS[job["variant"]]
    algorithm = algorithm_class(algorithm_name)
    kwargs = dict(kwargs)
    if kwargs.pop("paper", False):
        kwargs = paper_kwargs(job, kwargs)
    if job.get("learning_starts") is not None:
        kwargs["learning_starts"] = job["learning_starts"]
    eval_env = gym.make(job["env"], **evaluation_env_kwargs(job["env"], job["env_kwargs"]))
    folder = checkpoint_dir(out, job["env"], job["variant"], job["seed"])
    rows: list[dict[str, Any]] = []
    elapsed = 0.0
    recover_checkpoint(folder)
    if job["checkpoint_freq"] and (folder / "state.pkl").exists():
        model, rows, elapsed = load_checkpoint(algorithm, folder, job["device"])
        check_regime(model, job, folder)
        print(f"{folder}: resumed at {model.num_timesteps} steps", flush=True)
    else:
        model = new_model(job, algorithm, kwargs)
    resumed_at = model.num_timesteps
    start = time.perf_counter() - elapsed

    def evaluate() -> None:
        returns, lengths, successes, collisions, off_road = [], [], [], [], []
        vec_normalize = model.get_vec_normalize_env()
        for episode in range(job["eval_episodes"]):
            observation, _ = eval_env.reset(seed=10_000 * job["seed"] + episode)
            done, total, length, info = False, 0.0, 0, {}
            while not done:
                if vec_normalize is not None:
                    observation = vec_normalize.normalize_obs(observation)
                action, _ = model.predict(observation, deterministic=True)
                observation, reward, terminated, truncated, info = eval_env.step(action)
                total += float(reward)
                length += 1
                done = terminated or truncated
            returns.append(total)
            lengths.append(length)
            successes.append(float(info.get("is_success", np.nan)))
            collisions.append(float(info.get("collision", np.nan)))
            off_road.append(float(info.get("off_road", np.nan)))
        spread = model.logger.name_to_value.get("train/action_spread", np.nan)
        # the temperature: SAC's and DSAC's log_ent_coef, DACER-F's and DACER's actor.log_alpha
        log_alpha = getattr(model, "log_ent_coef", None)
        log_alpha = getattr(getattr(model, "actor", None), "log_alpha", None) if log_alpha is None else log_alpha
        rows.append(
            dict(
                env=job["env"],
                variant=job["variant"],
                seed=job["seed"],
                timesteps=model.num_timesteps,
                env_steps=model.num_timesteps,
                gradient_steps=model._n_updates,
                mean_return=float(np.mean(returns)),
                episode_length=float(np.mean(lengths)),
                arrival_rate=float(np.mean(successes)),
                collision_rate=float(np.mean(collisions)),
                off_road_rate=float(np.mean(off_road)),
                action_spread=float(spread),
                ent_coef=float(log_alpha.detach().exp()) if log_alpha is not None else np.nan,
                wall_seconds=time.perf_counter() - start,
                commit=job["commit"],
            )
        )
        path.parent.mkdir(parents=True, exist_ok=True)
        pd.DataFrame(rows).to_csv(path, index=False)
        print(json.dumps(rows[-1]), flush=True)

    class EvaluateAndCheckpoint(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps % job["eval_freq"] == 0:
                evaluate()
            return True

        def _on_rollout_start(self) -> None:
            # Between the gradient steps of one environment step and the next one: the point a resumed run starts from
            steps = self.num_timesteps
            if job["checkpoint_freq"] and steps > resumed_at and steps % job["checkpoint_freq"] == 0:
                save_checkpoint(self.model, folder, rows, time.perf_counter() - start)

    model.learn(job["timesteps"] - model.num_timesteps, callback=EvaluateAndCheckpoint(), reset_num_timesteps=resumed_at == 0)
    if job["checkpoint_freq"] and model.num_timesteps > resumed_at:
        # The finished model, the one the last evaluation describes (benchmarks/export_driver.py ships it)
        save_checkpoint(model, folder, rows, time.perf_counter() - start)
    model.get_env().close()  # with --vec-env subproc, ends the environments' processes
    return rows


def bootstrap_interval(values: np.ndarray, rng: np.random.Generator, n_resamples: int = 2000) -> tuple[float, float]:
    """95% percentile-bootstrap interval of the mean over seeds."""
    if len(values) < 2:
        return float(values.mean()), float(values.mean())
    means = rng.choice(values, size=(n_resamples, len(values)), replace=True).mean(axis=1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


X_AXES = {"env_steps": "environment steps", "gradient_steps": "gradient steps"}


def report(rows: list[dict[str, Any]], env_id: str, out: Path, x_axis: str = "env_steps") -> str:
    """
    Plot the curves of ``rows`` (mean and 95% bootstrap interval over seeds) to ``<out>/<env>.png``, or
    ``<out>/<env>-gradient_steps.png`` against gradient steps, write them all to ``<out>/<env>.csv`` and return the
    markdown table of the final evaluations.

    :param rows: evaluation rows of the runs (``run_one``'s)
    :param env_id: the environment, for the title and the file names
    :param out: the results folder
    :param x_axis: ``"env_steps"`` (transitions; runs written before the column existed have ``timesteps``) or
        ``"gradient_steps"``
    :return: the table
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    frame = pd.DataFrame(rows)
    if x_axis not in X_AXES:
        raise ValueError(f"x_axis {x_axis!r}: choose one of {', '.join(X_AXES)}")
    if "env_steps" not in frame:
        frame["env_steps"] = frame["timesteps"]
    frame["env_steps"] = frame["env_steps"].fillna(frame["timesteps"])
    if x_axis not in frame or frame[x_axis].isna().any():
        missing = sorted(frame.variant[frame[x_axis].isna()].unique()) if x_axis in frame else sorted(frame.variant.unique())
        raise SystemExit(f"runs of {missing} have no {x_axis} column: plot them against env_steps, or train them again")
    rng = np.random.default_rng(0)
    rates = ("arrival_rate", "collision_rate", "off_road_rate")  # off_road_rate: runs from 2026-11-23 on
    metrics = ["mean_return"] + [m for m in rates if m in frame and frame[m].notna().any()]
    figure, axes = plt.subplots(1, len(metrics), figsize=(5.5 * len(metrics), 3.8), squeeze=False)
    lines = [
        "| variant | seeds | steps | gradient steps | final return (mean [95% CI]) | "
        + " | ".join(m.replace("_", " ") for m in metrics[1:])
        + (" | " if len(metrics) > 1 else "")
        + "action spread | train minutes |",
        "|---|---|---|---|---|" + "---|" * (len(metrics) - 1) + "---|---|",
    ]
    for variant, group in frame.groupby("variant", sort=False):
        curve = group.groupby(x_axis)
        for axis, metric in zip(axes[0], metrics, strict=True):
            steps = np.array(sorted(curve.groups))
            values = [curve.get_group(step)[metric].to_numpy() for step in steps]
            intervals = np.array([bootstrap_interval(v, rng) for v in values])
            axis.plot(steps, [v.mean() for v in values], label=variant)
            axis.fill_between(steps, intervals[:, 0], intervals[:, 1], alpha=0.2)
            axis.set_xlabel(X_AXES[x_axis])
            axis.set_ylabel(metric.replace("_", " "))
        final = group[group.timesteps == group.timesteps.max()]
        updates = final.gradient_steps.mean() if "gradient_steps" in final else np.nan
        low, high = bootstrap_interval(final.mean_return.to_numpy(), rng)
        cells = [f"{final[m].mean():.2f}" for m in metrics[1:]]
        lines.append(
            f"| {variant} | {final.seed.nunique()} | {int(final.timesteps.max())} | "
            + ("n/a | " if np.isnan(updates) else f"{updates:.0f} | ")
            + f"{final.mean_return.mean():.1f} [{low:.1f}, {high:.1f}] | "
            + "".join(f"{c} | " for c in cells)
            + f"{final.action_spread.mean():.3f} | {final.wall_seconds.mean() / 60:.1f} |"
        )
    axes[0][0].legend()
    figure.suptitle(f"{env_id}: deterministic evaluation\nmean and 95% bootstrap CI over seeds", fontsize=10)
    figure.tight_layout()
    stem = env_id.replace("/", "_")
    figure.savefig(out / plot_name(env_id, x_axis), dpi=110)
    frame.to_csv(out / f"{stem}.csv", index=False)
    return "\n".join(lines)


def collect_runs(folder: Path, variants: list[str]) -> list[dict[str, Any]]:
    """Rows of every per-run CSV of ``variants`` in ``folder`` (``<variant>-seed<k>.csv``), variant by variant."""
    return [
        row
        for variant in variants
        for path in sorted(folder.glob(f"{variant}-seed*.csv"))
        if path.name[len(variant) + len("-seed") : -len(".csv")].isdigit()
        for row in read_rows(path)
    ]


def plot_name(env_id: str, x_axis: str) -> str:
    """The file name of ``report``'s plot."""
    stem = env_id.replace("/", "_")
    return f"{stem}.png" if x_axis == "env_steps" else f"{stem}-{x_axis}.png"


def check_regime_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """
    Refuse a ``--steps-per-gradient`` that does not fit ``--n-envs``, the variants or the step counts, and a
    ``--vec-env subproc`` that cannot run, with argparse's usage message and exit status 2.
    """
    from sb3_dacerf.common.regime import steps_per_gradient_kwargs, transitions_per_rollout

    if args.vec_env == "subproc" and (args.checkpoint_freq or args.workers > 1):
        parser.error(
            "--vec-env subproc: its environments run in other processes and cannot be pickled into a checkpoint, and "
            "the --workers pool's processes cannot start processes: pass --checkpoint-freq 0 and --workers 1 (or use "
            "--vec-env dummy)"
        )
    if args.steps_per_gradient is None:
        return
    try:
        regime = steps_per_gradient_kwargs(args.steps_per_gradient, args.n_envs)
    except ValueError as error:
        parser.error(f"--steps-per-gradient / --n-envs: {error}")
    own = sorted({v for v in args.variants if {"train_freq", "gradient_steps"} & set(VARIANTS.get(v, ("", {}))[1])})
    if own:
        parser.error(f"variants {own} set their own gradient steps: leave out --steps-per-gradient, or train them apart")
    rollout = transitions_per_rollout(args.steps_per_gradient, args.n_envs)
    counts = (("--timesteps", args.timesteps), ("--checkpoint-freq", args.checkpoint_freq))
    uneven = [f"{name} {value}" for name, value in counts if value % rollout]
    if uneven:
        # learn() stops, and checkpoints are taken, only between rollouts of train_freq * n_envs transitions
        parser.error(
            f"{', '.join(uneven)} not a multiple of the {rollout} transitions of a rollout (train_freq "
            f"{regime['train_freq']} x --n-envs {args.n_envs}): choose multiples of {rollout}"
        )


def main() -> None:
    from sb3_dacerf.envs.driving import DRIVING_ENV_IDS

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument(
        "--variants",
        nargs="+",
        default=["dacerf", "sac"],
        help=f"variants to train (with --report-only: any variant names found under --out): {', '.join(VARIANTS)}",
    )
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--timesteps", type=int, default=20_000)
    parser.add_argument("--eval-freq", type=int, default=2_000)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--workers", type=int, default=2, help="parallel training processes (1: in this process)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--env-kwargs",
        type=json.loads,
        default={},
        help='keyword arguments of gym.make, as JSON, e.g. \'{"config": {"collision_penalty": 500}}\' (use another --out)',
    )
    parser.add_argument(
        "--train-env-kwargs",
        type=json.loads,
        default={},
        help="keyword arguments of gym.make for the training env only, merged over --env-kwargs (config keys one by "
        'one), e.g. \'{"config": {"reference_start_probability": 0}}\' (the intersection\'s standard starts, as '
        "evaluations have them): evaluations keep --env-kwargs",
    )
    parser.add_argument("--out", help="results folder (default: benchmarks/results, with --quick benchmarks/results/quick)")
    parser.add_argument("--first-seed", type=int, default=0, help="seeds are first-seed .. first-seed + seeds - 1")
    parser.add_argument(
        "--checkpoint-freq",
        type=int,
        default=5_000,
        help="save each run every that many steps under <out>/checkpoints (0: never); a repeated command resumes from there",
    )
    parser.add_argument("--learning-starts", type=int, help="override every variant's learning_starts")
    parser.add_argument(
        "--n-envs",
        type=int,
        default=1,
        help="training environments stepped together: N transitions per rollout step, then the variant's gradient "
        "steps (use another --out); --eval-freq and --checkpoint-freq must be multiples of N",
    )
    parser.add_argument(
        "--steps-per-gradient",
        help="the data regime: S environment steps (transitions) per gradient step, a multiple of --n-envs (the "
        "paper's sample batch size, 200), or 1/G for G gradient steps per transition (default: one gradient step per "
        "step of the --n-envs environments); sets train_freq and gradient_steps (use another --out)",
    )
    parser.add_argument(
        "--vec-env",
        choices=["dummy", "subproc"],
        default="dummy",
        help="how the --n-envs environments are stepped: in this process (DummyVecEnv) or one process each "
        "(SubprocVecEnv, one core each; needs --checkpoint-freq 0 and --workers 1)",
    )
    parser.add_argument(
        "--x-axis",
        choices=["env_steps", "gradient_steps"],
        default="env_steps",
        help="what the plots' x axis counts (gradient_steps: <env>-gradient_steps.png)",
    )
    parser.add_argument(
        "--vec-normalize",
        nargs="?",
        const="plain",
        choices=["plain", "masked"],
        help="normalise observations with VecNormalize(norm_obs=True, norm_reward=False), statistics saved in the "
        "checkpoints; 'masked' (driving scenarios): sb3_dacerf.common.vec_normalize.MaskedVecNormalize, whose empty "
        'vehicle rows stay zeros at any traffic density (e.g. with --env-kwargs \'{"density": "random"}\')',
    )
    parser.add_argument(
        "--normalize-reward",
        action="store_true",
        help="with --vec-normalize's observations, also scale the training rewards by VecNormalize's running return "
        "std (norm_reward=True); evaluations report the raw returns",
    )
    parser.add_argument("--quick", action="store_true", help="2 seeds, 3k steps: checks the pipeline in minutes")
    parser.add_argument(
        "--report-only", action="store_true", help="train nothing: report the runs of --variants found under --out"
    )
    args = parser.parse_args()
    if args.workers < 1:
        parser.error(f"--workers must be at least 1, got {args.workers}")
    unknown = [variant for variant in args.variants if variant not in VARIANTS]
    if unknown and not args.report_only:
        parser.error(f"unknown variants {unknown}: choose from {', '.join(VARIANTS)} (or use --report-only for older runs)")
    if args.quick:
        args.seeds, args.timesteps, args.eval_freq, args.eval_episodes = 2, 3_000, 1_000, 3
    if args.n_envs < 1:
        parser.error(f"--n-envs must be at least 1, got {args.n_envs}")

    if args.vec_normalize == "masked" and args.env not in DRIVING_ENV_IDS:
        parser.error(
            f"--vec-normalize masked normalises the vehicle rows of a driving scenario ({', '.join(DRIVING_ENV_IDS)}); "
            f"{args.env} has none: pass --vec-normalize alone"
        )
    check_regime_args(parser, args)
    frequencies = (("--eval-freq", args.eval_freq), ("--checkpoint-freq", args.checkpoint_freq))
    uneven = [f"{name} {value}" for name, value in frequencies if value % args.n_envs]
    if uneven:
        # Steps advance by n_envs transitions: a frequency that is not a multiple would never be hit exactly
        parser.error(f"{', '.join(uneven)} not a multiple of --n-envs {args.n_envs}: choose multiples of it")

    out = Path(args.out or ("benchmarks/results/quick" if args.quick else "benchmarks/results"))
    out.mkdir(parents=True, exist_ok=True)
    folder = run_file(out, args.env, "x", 0).parent
    if args.report_only:
        rows = collect_runs(folder, args.variants)
        if not rows:
            raise SystemExit(f"No runs of {args.variants} under {folder}: run without --report-only first")
        print(f"\n{args.env}: runs found under {folder}\n")
        print(report(rows, args.env, out, args.x_axis))
        print(f"\nsaved {out / args.env.replace('/', '_')}.csv and {plot_name(args.env, args.x_axis)}")
        return
    commit = checkout_commit()
    jobs = [
        dict(
            commit=commit,
            env=args.env,
            variant=variant,
            seed=seed,
            timesteps=args.timesteps,
            eval_freq=args.eval_freq,
            eval_episodes=args.eval_episodes,
            device=args.device,
            out=str(out),
            env_kwargs=args.env_kwargs,
            train_env_kwargs=args.train_env_kwargs,
            checkpoint_freq=args.checkpoint_freq,
            learning_starts=args.learning_starts,
            vec_normalize=args.vec_normalize,
            normalize_reward=args.normalize_reward,
            n_envs=args.n_envs,
            steps_per_gradient=args.steps_per_gradient,
            vec_env=args.vec_env,
        )
        for seed in range(args.first_seed, args.first_seed + args.seeds)
        for variant in args.variants
    ]
    if args.workers == 1:
        for job in jobs:  # in this process: stopping it stops the training, nothing is left running
            run_one(job)
    else:
        # A plain `kill` of this process ends the pool's workers too (SystemExit leaves the `with`, which terminates
        # them) instead of leaving them training on as orphans.
        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
        with mp.get_context("spawn").Pool(args.workers) as pool:
            pool.map(run_one, jobs, chunksize=1)
    # The summary covers every run of this environment under --out, not only this command's, so a comparison
    # run in pieces (one variant or seed range at a time) always ends with a complete <env>.csv and plot.
    trained = list(dict.fromkeys(args.variants))
    others = sorted({path.name.rsplit("-seed", 1)[0] for path in folder.glob("*-seed*.csv")} - set(trained))
    rows = collect_runs(folder, trained + others)
    print(f"\n{args.env}: every run under {folder} (this command: {args.timesteps} steps, {args.seeds} seeds)\n")
    print(report(rows, args.env, out, args.x_axis))
    print(f"\nsaved {out / args.env.replace('/', '_')}.csv and {plot_name(args.env, args.x_axis)}")


if __name__ == "__main__":
    main()
