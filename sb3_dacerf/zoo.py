"""
RL Zoo plug-in (see the "RL Zoo" page): ``python -m rl_zoo3.train --algo dacerf|dacer|dsac --env <id>``, ``enjoy``,
``record_video`` and ``-optimize`` with this package's ``hyperparams/<algo>.yml``. The start-up hook
``sb3_dacerf_zoo_hook`` (``pip install .``) calls :func:`register` on each RL Zoo module as it is imported; without
it, ``python -m sb3_dacerf.zoo train ...`` does the same.
"""

import argparse
import contextlib
import copy
import functools
import importlib
import inspect
import io
import os
import random
import runpy
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import optuna
import torch as th
import yaml
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.save_util import recursive_getattr
from stable_baselines3.common.vec_env import VecEnv

from sb3_dacerf import DACER, DACERF, DSAC
from sb3_dacerf.common.policies import CRITICS
from sb3_dacerf.common.vec_normalize import MaskedVecNormalize

Params = dict[str, Any]

# Wheels ship the YAML files inside the package; source checkouts and editable installs keep them at the repository root
HYPERPARAMS_DIR = Path(__file__).parent / "hyperparams"
if not HYPERPARAMS_DIR.is_dir():
    HYPERPARAMS_DIR = Path(__file__).parent.parent / "hyperparams"

#: The algorithms this package adds to RL Zoo, by their ``--algo`` name
ALGORITHMS = {"dacerf": DACERF, "dacer": DACER, "dsac": DSAC}

# Same names as RL Zoo's off-policy samplers
NET_ARCH = {"small": [64, 64], "medium": [256, 256], "big": [400, 300], "large": [256, 256, 256], "verybig": [512, 512, 512]}


def sample_optimisation_params(trial: optuna.Trial) -> Params:
    """The settings every sampler draws first: learning rate, ``batch_size_pow`` (batch size 128 to 1024), τ, policy delay."""
    sampled = {
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 1e-3, log=True),
        "batch_size_pow": trial.suggest_int("batch_size_pow", 7, 10),
        "tau": trial.suggest_float("tau", 1e-4, 0.02, log=True),
        "policy_delay": trial.suggest_int("policy_delay", 1, 5),
    }
    trial.set_user_attr("batch_size", 2 ** sampled["batch_size_pow"])
    return sampled


def convert_dacer_params(sampled_params: Params, policy_kwargs: Params | None = None) -> Params:
    """DACER's arguments from an Optuna trial's ``params`` (``--trial-id``), updating the YAML entry's ``policy_kwargs``."""
    hyperparams = sampled_params.copy()
    hyperparams["batch_size"] = 2 ** hyperparams.pop("batch_size_pow")
    hyperparams["policy_kwargs"] = {**(policy_kwargs or {}), "net_arch": NET_ARCH[hyperparams.pop("net_arch")]}
    for name in ("n_diffusion_steps", "n_sampling_steps"):  # policy arguments
        if name in hyperparams:
            hyperparams["policy_kwargs"][name] = hyperparams.pop(name)
    return hyperparams


def convert_dacerf_params(sampled_params: Params, policy_kwargs: Params | None = None) -> Params:
    """DACERF's arguments from an Optuna trial's ``params`` (:func:`sample_dacerf_params`), as :func:`convert_dacer_params`."""
    hyperparams = convert_dacer_params(sampled_params, policy_kwargs)
    if "critics" in hyperparams:  # the draw overrides the YAML entry's critics
        critics = hyperparams.pop("critics")
        if critics not in CRITICS:
            raise ValueError(f"Unknown critics {critics!r} in the sampled parameters: use one of {sorted(CRITICS)}")
        hyperparams["policy_kwargs"]["critic"] = critics
    if hyperparams.get("ent_coef") == "off":  # Optuna's categorical values: "auto" (learned α) or "off" (paper)
        hyperparams["ent_coef"] = 0.0
    return hyperparams


def convert_dsac_params(sampled_params: Params, policy_kwargs: Params | None = None) -> Params:
    """DSAC's arguments from an Optuna trial's ``params`` (:func:`sample_dsac_params`): ``ent_coef="auto_<initial_ent_coef>"``."""
    hyperparams = convert_dacer_params(sampled_params, policy_kwargs)
    if "initial_ent_coef" in hyperparams:
        hyperparams["ent_coef"] = f"auto_{hyperparams.pop('initial_ent_coef')}"
    return hyperparams


def sample_dacerf_params(trial: optuna.Trial, *_: Any, policy_kwargs: Params | None = None) -> Params:
    """RL Zoo's ``HYPERPARAMS_SAMPLER`` for DACERF, around the paper's values, keeping the YAML entry's ``policy_kwargs``."""
    sampled = {
        **sample_optimisation_params(trial),
        "langevin_steps": trial.suggest_int("langevin_steps", 5, 40, step=5),
        "langevin_step_size": trial.suggest_float("langevin_step_size", 0.003, 0.3, log=True),
        "langevin_temperature": trial.suggest_float("langevin_temperature", 0.001, 0.1, log=True),
        "n_sampling_steps": trial.suggest_categorical("n_sampling_steps", [1, 2, 4, 8]),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCH)),
        "ent_coef": trial.suggest_categorical("ent_coef", ["auto", "off"]),
        "flow_matching_weights": trial.suggest_categorical("flow_matching_weights", ["gain", "paper"]),
        "critics": trial.suggest_categorical("critics", list(CRITICS)),
        "n_steps": trial.suggest_categorical("n_steps", [1, 3, 5]),
    }
    return convert_dacerf_params(sampled, policy_kwargs)


def sample_dacer_params(trial: optuna.Trial, *_: Any, policy_kwargs: Params | None = None) -> Params:
    """RL Zoo's ``HYPERPARAMS_SAMPLER`` for DACER, as :func:`sample_dacerf_params`: DACER's diffusion and temperature settings."""
    sampled = {
        **sample_optimisation_params(trial),
        "n_diffusion_steps": trial.suggest_categorical("n_diffusion_steps", [5, 10, 20]),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCH)),
        "alpha_learning_rate": trial.suggest_float("alpha_learning_rate", 1e-3, 0.1, log=True),
        "alpha_update_interval": trial.suggest_categorical("alpha_update_interval", [1_000, 5_000, 10_000]),
    }
    return convert_dacer_params(sampled, policy_kwargs)


def sample_dsac_params(trial: optuna.Trial, *_: Any, policy_kwargs: Params | None = None) -> Params:
    """RL Zoo's ``HYPERPARAMS_SAMPLER`` for DSAC, as :func:`sample_dacerf_params`, around the authors' values."""
    sampled = {
        **sample_optimisation_params(trial),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCH)),
        "initial_ent_coef": trial.suggest_categorical("initial_ent_coef", [0.1, 1.0, 2.718]),  # authors: e
        "alpha_learning_rate": trial.suggest_float("alpha_learning_rate", 3e-5, 3e-3, log=True),
        "tau_b": trial.suggest_float("tau_b", 1e-4, 0.05, log=True),
    }
    return convert_dsac_params(sampled, policy_kwargs)


#: Each algorithm's Optuna sampler and its converter (RL Zoo's ``HYPERPARAMS_SAMPLER`` and ``HYPERPARAMS_CONVERTER``)
SAMPLERS = {"dacerf": sample_dacerf_params, "dacer": sample_dacer_params, "dsac": sample_dsac_params}
CONVERTERS = {"dacerf": convert_dacerf_params, "dacer": convert_dacer_params, "dsac": convert_dsac_params}


def default_config(algo: str, env_id: str) -> str | None:
    """The YAML file RL Zoo reads without ``--conf-file``: this package's ``hyperparams/<algo>.yml`` for its algorithms
    or where it has an entry for ``env_id`` (SAC on ``DMC-*`` ids), else ``None`` (RL Zoo's own)."""
    path = HYPERPARAMS_DIR / f"{algo}.yml"
    if algo in ALGORITHMS or (path.is_file() and env_id in yaml.safe_load(path.read_text())):
        return str(path)
    return None


def masked_normalization(normalize_kwargs: Params) -> bool:
    """Take ``masked`` out of RL Zoo's ``normalize`` arguments (``normalize: "dict(norm_obs=True, masked=True)"`` in a
    YAML entry): whether :class:`MaskedVecNormalize` normalises the observations instead of ``VecNormalize``."""
    masked = normalize_kwargs.pop("masked", False)
    if not isinstance(masked, bool):
        raise ValueError(f"normalize: masked={masked!r}: write masked=True (MaskedVecNormalize) or leave it out")
    if masked and not normalize_kwargs.get("norm_obs", True):
        raise ValueError(
            "normalize: masked=True normalises the observations' vehicle rows, but norm_obs=False turns observation "
            "normalisation off: drop norm_obs=False, or masked=True"
        )
    return masked


def masked_rows(venv: VecEnv, env_id: str) -> tuple[int, int, int]:
    """The vehicle rows of a driving env's observation (``rows`` of :class:`MaskedVecNormalize`), from its config."""
    from sb3_dacerf.envs.driving.common.observation import vehicle_rows  # (highway-env: the driving extra)

    try:
        return vehicle_rows(venv.get_attr("config")[0])
    except (AttributeError, KeyError, TypeError) as error:
        raise ValueError(
            "normalize: masked=True normalises the vehicle rows of a driving env's observation (DACERF-Multilane-v0, "
            f"DACERF-Intersection-v0), but {env_id} has no driving config ({error!r}): drop masked=True for it"
        ) from error


class ParallelTraining:
    """
    RL Zoo's ``ParallelTrainCallback`` for a ``model`` of :data:`ALGORITHMS`: a copy of it, the *trainer*, takes rounds
    of gradient steps in a thread on copies of the replay buffer while the model collects transitions; between rounds,
    the trainer's parameters go to the model. :meth:`close` gives the model its ``train()`` and ``save()`` back.
    """

    def __init__(self, model: OffPolicyAlgorithm):
        self.model = model
        with io.BytesIO() as file:
            model.save(file)
            file.seek(0)
            self.trainer: OffPolicyAlgorithm = type(model).load(file, device=model.device)
        # Its own logger: the thread must not write into the dictionaries the main thread dumps
        self.trainer.set_logger(Logger(folder=None, output_formats=[]))
        self.thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.has_news = False  # whether the trainer has trained since the model last received its parameters
        self._instance_methods: Params = {name: vars(model)[name] for name in ("train", "save") if name in vars(model)}
        model.train = lambda gradient_steps, batch_size=64: None  # type: ignore[method-assign,misc]
        model.save = self.save  # type: ignore[method-assign]

    @property
    def running(self) -> bool:
        """Whether a round of gradient steps is under way in the thread."""
        return self.thread is not None and self.thread.is_alive()

    def wait(self) -> None:
        """Wait for the running round, if any; raise the error that stopped it, if one did."""
        if self.thread is not None:
            self.thread.join()
            self.thread = None
        if self.error is not None:
            error, self.error = self.error, None
            raise error

    def _copy_progress(self) -> None:
        for name in ("num_timesteps", "_total_timesteps", "_episode_num", "_current_progress_remaining"):
            setattr(self.trainer, name, getattr(self.model, name))

    def exchange(self) -> None:
        """With the trainer idle: its parameters, update count and logged values go to the model (if it has trained since)."""
        assert not self.running, "the trainer's parameters are read while it trains"
        if not self.has_news:
            return
        self.has_news = False
        # SB3 annotates set_parameters' argument narrower than what get_parameters returns (state dicts)
        parameters: Any = copy.deepcopy(self.trainer.get_parameters())
        self.model.set_parameters(parameters, device=self.model.device)
        for name in self.trainer._get_torch_save_params()[1]:  # tensors saved apart from state dicts (SAC's log_ent_coef)
            recursive_getattr(self.model, name).data.copy_(recursive_getattr(self.trainer, name).data)
        self.model._n_updates = self.trainer._n_updates
        logged = self.trainer.logger
        for key, value in logged.name_to_value.items():
            self.model.logger.record(key, value, exclude=logged.name_to_excluded.get(key))
        self.trainer.set_logger(Logger(folder=None, output_formats=[]))  # empty for the next round

    def start(self, gradient_steps: int, batch_size: int) -> None:
        """Give the idle trainer copies of the replay buffer, statistics and progress, and start a round in a thread."""
        assert not self.running, "a round of gradient steps is already running"
        self.trainer.replay_buffer = copy.deepcopy(self.model.replay_buffer)
        # A copy without the environments (VecNormalize does not pickle them): statistics as of this buffer
        self.trainer._vec_normalize_env = copy.deepcopy(self.model.get_vec_normalize_env())
        self._copy_progress()
        self.has_news = True
        self.thread = threading.Thread(target=self._train, args=(gradient_steps, batch_size), daemon=True)
        self.thread.start()

    def _train(self, gradient_steps: int, batch_size: int) -> None:
        try:
            self.trainer.train(gradient_steps=gradient_steps, batch_size=batch_size)
        except BaseException as error:
            self.error = error

    def save(self, *args: Any, **kwargs: Any) -> None:
        """The model's ``save()`` while it learns: the trainer's parameters, with the model's progress."""
        self.wait()
        self._copy_progress()
        self.trainer.save(*args, **kwargs)

    def close(self) -> None:
        """Wait for the last round; give the model the trainer's parameters and its ``train()``, ``save()`` back (idempotent)."""
        for name in ("train", "save"):
            vars(self.model).pop(name, None)
        vars(self.model).update(self._instance_methods)
        self.wait()
        self.exchange()


def _patch(cls: type, **wrappers: Callable[..., Any]) -> None:
    """Wrap methods of an RL Zoo class, once: ``cls.<name>(self, ...)`` calls ``wrappers[name](self, original, ...)``."""
    if getattr(cls, "_sb3_dacerf_patched", False):
        return
    for name, wrapper in wrappers.items():
        setattr(cls, name, functools.partialmethod(wrapper, getattr(cls, name)))
    cls._sb3_dacerf_patched = True  # type: ignore[attr-defined]


def _init(self: Any, init: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
    init(self, *args, **kwargs)
    if inspect.signature(init).bind(self, *args, **kwargs).arguments.get("config") is None:  # no --conf-file
        self.config = default_config(self.algo, self.env_name.gym_id) or self.config


def _maybe_normalize(self: Any, maybe_normalize: Callable[..., VecEnv], env: VecEnv, eval_env: bool) -> VecEnv:
    kwargs = dict(self.normalize_kwargs)  # (RL Zoo's may be the entry's own dict, which it saves)
    saved = os.path.join(os.path.dirname(self.trained_agent), self.env_name, "vecnormalize.pkl")
    if not masked_normalization(kwargs) or os.path.exists(saved):
        self.normalize_kwargs = kwargs
        return maybe_normalize(self, env, eval_env)  # (saved statistics load as the class that saved them)
    if eval_env:  # as RL Zoo's evaluation env: statistics copied from the training env, rewards as they are
        kwargs.update(norm_reward=False, training=False)
    if self.verbose > 0:
        print(f"Normalization activated: MaskedVecNormalize {kwargs}")
    return MaskedVecNormalize(env, rows=masked_rows(env, self.env_name.gym_id), **kwargs)


def _hyperparameters_optimization(self: Any, optimize: Callable[..., Any]) -> None:
    """
    RL Zoo's ``-optimize``, its samplers keeping the YAML entry's ``policy_kwargs``. On a database ``--storage``, trials
    record Optuna's heartbeat every ``SB3_DACERF_OPTUNA_HEARTBEAT`` seconds (60 by default, 0: none), and workers that
    race to create Optuna's tables on a new database try again.
    """
    if self.algo in ALGORITHMS:
        from rl_zoo3.hyperparams_opt import HYPERPARAMS_SAMPLER

        # RL Zoo replaces the YAML's policy_kwargs with the sampled ones: merge instead, to keep the optimizer
        policy_kwargs = self._hyperparams.get("policy_kwargs")
        HYPERPARAMS_SAMPLER[self.algo] = functools.partial(SAMPLERS[self.algo], policy_kwargs=policy_kwargs)
    if not isinstance(self.storage, str) or "://" not in self.storage or self.storage.endswith(".log"):  # no database
        return optimize(self)
    value = os.environ.get("SB3_DACERF_OPTUNA_HEARTBEAT", "60")
    if not value.strip().isdecimal():
        raise ValueError(f"SB3_DACERF_OPTUNA_HEARTBEAT={value!r}: give a whole number of seconds (0 turns the heartbeat off).")
    interval = int(value)
    import sqlalchemy.exc

    create_study = optuna.create_study

    @functools.wraps(create_study)
    def create_study_on_database(*args: Any, storage: Any = None, **kwargs: Any) -> optuna.Study:
        for attempt in range(5):
            try:
                database = optuna.storages.RDBStorage(storage, heartbeat_interval=interval or None)
                break
            except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError):
                if attempt == 4:
                    raise
                time.sleep(random.uniform(0.5, 2.0))
        return create_study(*args, storage=database, **kwargs)

    optuna.create_study = create_study_on_database
    try:
        optimize(self)
    finally:
        optuna.create_study = create_study


def _init_callback(self: Any, init_callback: Callable[..., Any]) -> None:
    if not any(isinstance(self.model, algorithm) for algorithm in ALGORITHMS.values()):
        return init_callback(self)
    training = self._sb3_dacerf_parallel_training = ParallelTraining(self.model)
    # The attributes RL Zoo's callback reads or offers
    self._model, self.model_class, self.batch_size = training.trainer, type(self.model), training.trainer.batch_size


def _on_rollout_end(self: Any, on_rollout_end: Callable[..., Any]) -> None:
    training: ParallelTraining | None = vars(self).get("_sb3_dacerf_parallel_training")
    if training is None:
        return on_rollout_end(self)
    if not training.running:
        training.wait()  # the round that just ended: raise its error, if any
        training.exchange()
        if self.num_timesteps >= training.trainer.learning_starts:
            training.start(self.gradient_steps, self.batch_size)


def _on_training_end(self: Any, on_training_end: Callable[..., Any]) -> None:
    training: ParallelTraining | None = vars(self).get("_sb3_dacerf_parallel_training")
    if training is None:
        return on_training_end(self)
    if self.verbose > 0 and training.running:
        print("Waiting for training thread to terminate")
    training.close()


def choose_threads(argv: Sequence[str]) -> None:
    """Give PyTorch one thread when RL Zoo's arguments ``argv`` run one of :data:`ALGORITHMS` without ``--num-threads``."""
    parser = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    parser.add_argument("--algo")
    parser.add_argument("--num-threads")
    with contextlib.suppress(argparse.ArgumentError):  # RL Zoo's own parser reports it
        known, _ = parser.parse_known_args(argv)
        if known.algo in ALGORITHMS and known.num_threads is None:
            th.set_num_threads(1)


def register(module: ModuleType) -> None:
    """Add DACERF, DACER and DSAC to an RL Zoo module (idempotent): ``rl_zoo3.utils`` (and :func:`choose_threads` of
    ``sys.argv``), ``rl_zoo3.hyperparams_opt``, ``rl_zoo3.exp_manager`` or ``rl_zoo3.callbacks``; others are left alone."""
    if module.__name__ == "rl_zoo3.utils":
        module.ALGOS.update(ALGORITHMS)
        choose_threads(sys.argv[1:])
    elif module.__name__ == "rl_zoo3.hyperparams_opt":
        module.HYPERPARAMS_SAMPLER.update(SAMPLERS)
        module.HYPERPARAMS_CONVERTER.update(CONVERTERS)
    elif module.__name__ == "rl_zoo3.exp_manager":
        _patch(
            module.ExperimentManager,
            __init__=_init,
            _maybe_normalize=_maybe_normalize,
            hyperparameters_optimization=_hyperparameters_optimization,
        )
    elif module.__name__ == "rl_zoo3.callbacks":
        callbacks = {"_init_callback": _init_callback, "_on_rollout_end": _on_rollout_end, "_on_training_end": _on_training_end}
        _patch(module.ParallelTrainCallback, **callbacks)


def main() -> None:
    """``python -m sb3_dacerf.zoo <script> [args]``: run ``rl_zoo3.<script>`` (train, enjoy, ...) with DACERF, DACER and DSAC."""
    for name in ("utils", "hyperparams_opt", "exp_manager", "callbacks"):
        register(importlib.import_module(f"rl_zoo3.{name}"))
    if len(sys.argv) < 2:
        raise SystemExit("usage: python -m sb3_dacerf.zoo <train|enjoy|record_video|...> [RL Zoo arguments]")
    script = f"rl_zoo3.{sys.argv[1]}"
    sys.argv = [script, *sys.argv[2:]]
    runpy.run_module(script, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
