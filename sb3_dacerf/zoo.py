"""
RL Zoo integration: ``python -m rl_zoo3.train --algo dacerf --env <id>``, ``--algo dacer`` or ``--algo dsac`` (and ``enjoy``,
``record_video``, ``--optimize``) with no wrapper script and no ``--conf-file``: each algorithm reads its own
``hyperparams/<algo>.yml``.

With a database ``--storage`` (``postgresql://...``), ``-optimize`` studies get Optuna's trial heartbeat (every
``SB3_DACERF_OPTUNA_HEARTBEAT`` seconds, 60 by default, 0 for none): a trial whose worker was killed is marked FAIL
by the next worker that starts a trial, instead of staying RUNNING forever; and workers started at the same moment
on a new database no longer fail creating Optuna's tables.

RL Zoo leaves PyTorch at one thread per core unless ``--num-threads`` is given; a command whose ``--algo`` is DACERF,
DACER or DSAC gets one thread instead (see :func:`choose_threads`), unless it gives ``--num-threads``.

A YAML entry's ``normalize: "dict(norm_obs=True, norm_reward=False, masked=True)"`` (driving ids) normalises the
observations with :class:`~sb3_dacerf.common.vec_normalize.MaskedVecNormalize` (see :func:`masked_normalization`).

RL Zoo's ``ParallelTrainCallback`` (``-params callback:"'rl_zoo3.callbacks.ParallelTrainCallback'"``), gradient
steps in a thread while the environment steps, works with DACERF, DACER and DSAC as with SAC: see
:class:`ParallelTraining`.

RL Zoo fixes its ``--algo`` choices from ``rl_zoo3.utils.ALGOS`` before it imports ``--gym-packages``, so DACERF,
DACER and DSAC have to be there earlier: the start-up hook ``sb3_dacerf_zoo_hook`` (installed by ``pip install .``)
calls :func:`register` on ``rl_zoo3.utils``, ``rl_zoo3.hyperparams_opt``, ``rl_zoo3.exp_manager`` and
``rl_zoo3.callbacks`` as soon as each is imported. Where the hook is not installed, ``python -m sb3_dacerf.zoo train
--algo dacerf ...`` (any RL Zoo script name in place of ``train``) registers the algorithms and runs the script.

This module is imported only together with RL Zoo: it imports torch, Stable-Baselines3, DACERF, DACER and DSAC.
"""

import argparse
import contextlib
import copy
import functools
import inspect
import io
import os
import random
import runpy
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import optuna
import torch as th
import yaml
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.save_util import recursive_getattr
from stable_baselines3.common.vec_env import VecEnv

from sb3_dacerf import DACER, DACERF, DSAC
from sb3_dacerf.common.policies import CRITICS as _POLICY_CRITICS
from sb3_dacerf.common.vec_normalize import MaskedVecNormalize

if TYPE_CHECKING:
    from rl_zoo3.callbacks import ParallelTrainCallback
    from rl_zoo3.exp_manager import ExperimentManager

# Wheels ship the YAML files inside the package; source checkouts and editable installs keep them at the repository root
HYPERPARAMS_DIR = Path(__file__).parent / "hyperparams"
if not HYPERPARAMS_DIR.is_dir():
    HYPERPARAMS_DIR = Path(__file__).parent.parent / "hyperparams"

#: The algorithms this package adds to RL Zoo, by their ``--algo`` name
ALGORITHMS = {"dacerf": DACERF, "dacer": DACER, "dsac": DSAC}

# Same names as RL Zoo's off-policy samplers
NET_ARCH = {
    "small": [64, 64],
    "medium": [256, 256],
    "big": [400, 300],
    "large": [256, 256, 256],
    "verybig": [512, 512, 512],
}

#: The critics :func:`sample_dacerf_params` draws from (``policy_kwargs`` ``critic``): SB3's MLP, LayerNorm after every
#: hidden layer (the default), or CrossQ's batch renormalisation without target networks (needs sb3-contrib, which RL
#: Zoo installs). The draw overrides a YAML entry's own choice of critics.
CRITICS = _POLICY_CRITICS


def convert_dacerf_params(sampled_params: dict[str, Any], policy_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """
    Turn the values drawn by :func:`sample_dacerf_params` (an Optuna trial's ``params``) into DACERF arguments.

    :param sampled_params: Optuna parameters, as named in :func:`sample_dacerf_params`
    :param policy_kwargs: ``policy_kwargs`` of the YAML entry (optimizer, ...), which the sampled ``net_arch`` updates
    :return: keyword arguments for ``DACERF``
    """
    hyperparams = convert_dacer_params(sampled_params, policy_kwargs)  # the settings both samplers draw
    if "critics" in hyperparams:
        critics = hyperparams.pop("critics")
        if critics not in CRITICS:
            raise ValueError(f"Unknown critics {critics!r} in the sampled parameters: use one of {sorted(CRITICS)}")
        hyperparams["policy_kwargs"]["critic"] = critics
    if hyperparams.get("ent_coef") == "off":  # Optuna's categorical values: "auto" (learned α) or "off" (paper)
        hyperparams["ent_coef"] = 0.0
    return hyperparams


def sample_optimisation_params(trial: optuna.Trial) -> dict[str, Any]:
    """
    The optimisation settings both samplers draw first: learning rate, ``batch_size_pow`` (2**7 = 128 to
    2**10 = 1024), ``tau`` and ``policy_delay``.

    :param trial: Optuna trial
    :return: the drawn values, named as Optuna names them
    """
    return {
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 1e-3, log=True),
        "batch_size_pow": trial.suggest_int("batch_size_pow", 7, 10),
        "tau": trial.suggest_float("tau", 1e-4, 0.02, log=True),
        "policy_delay": trial.suggest_int("policy_delay", 1, 5),
    }


def sample_dacerf_params(
    trial: optuna.Trial,
    n_actions: int,
    n_envs: int,
    additional_args: dict[str, Any],
    policy_kwargs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """
    Sampler for DACERF hyper-parameters (RL Zoo's ``HYPERPARAMS_SAMPLER`` signature), centred on the paper's values.

    :param trial: Optuna trial
    :param n_actions: action dimension (unused: ``target_entropy="auto"`` already scales with it)
    :param n_envs: number of environments (unused)
    :param additional_args: RL Zoo's extra arguments (unused: no HER replay buffer for DACERF)
    :param policy_kwargs: ``policy_kwargs`` of the YAML entry, kept apart from the sampled ``net_arch``
    :return: keyword arguments for ``DACERF``
    """
    sampled: dict[str, Any] = {
        **sample_optimisation_params(trial),  # batch size from 128 to 1024 (paper: 512)
        "langevin_steps": trial.suggest_int("langevin_steps", 5, 40, step=5),
        "langevin_step_size": trial.suggest_float("langevin_step_size", 0.003, 0.3, log=True),
        "langevin_temperature": trial.suggest_float("langevin_temperature", 0.001, 0.1, log=True),
        "n_sampling_steps": trial.suggest_categorical("n_sampling_steps", [1, 2, 4, 8]),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCH)),
        # The entropy regulator (learned α, or the paper's mechanism without added noise), the actor-loss
        # weighting, the critics (CRITICS) and the normalised Langevin gradient: the options benchmarks/learning.md measures
        "ent_coef": trial.suggest_categorical("ent_coef", ["auto", "off"]),
        "flow_matching_weights": trial.suggest_categorical("flow_matching_weights", ["gain", "paper"]),
        "critics": trial.suggest_categorical("critics", list(CRITICS)),
        "langevin_normalize_gradient": trial.suggest_categorical("langevin_normalize_gradient", [False, True]),
        # one-step targets (the default, as in the paper) or n-step returns
        "n_steps": trial.suggest_categorical("n_steps", [1, 3, 5]),
    }
    trial.set_user_attr("batch_size", 2 ** sampled["batch_size_pow"])
    return convert_dacerf_params(sampled, policy_kwargs)


def convert_dacer_params(sampled_params: dict[str, Any], policy_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """
    Turn the values drawn by :func:`sample_dacer_params` (an Optuna trial's ``params``) into DACER arguments.
    :func:`convert_dacerf_params` starts from it: ``batch_size_pow`` and ``net_arch`` mean the same for both.

    :param sampled_params: Optuna parameters, as named in :func:`sample_dacer_params`
    :param policy_kwargs: ``policy_kwargs`` of the YAML entry, which the sampled ``net_arch`` updates
    :return: keyword arguments for ``DACER``
    """
    hyperparams = sampled_params.copy()
    hyperparams["batch_size"] = 2 ** hyperparams.pop("batch_size_pow")
    hyperparams["policy_kwargs"] = {**(policy_kwargs or {}), "net_arch": NET_ARCH[hyperparams.pop("net_arch")]}
    for name in ("n_diffusion_steps", "n_sampling_steps"):  # policy arguments
        if name in hyperparams:
            hyperparams["policy_kwargs"][name] = hyperparams.pop(name)
    return hyperparams


def sample_dacer_params(
    trial: optuna.Trial,
    n_actions: int,
    n_envs: int,
    additional_args: dict[str, Any],
    policy_kwargs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """
    Sampler for DACER hyper-parameters (RL Zoo's ``HYPERPARAMS_SAMPLER`` signature): the optimisation and the
    diffusion and entropy-regulator settings of the DACER paper, around their values.

    :param trial: Optuna trial
    :param n_actions: action dimension (unused: ``target_entropy="auto"`` already scales with it)
    :param n_envs: number of environments (unused)
    :param additional_args: RL Zoo's extra arguments (unused: no HER replay buffer for DACER)
    :param policy_kwargs: ``policy_kwargs`` of the YAML entry, kept apart from the sampled ``net_arch``
    :return: keyword arguments for ``DACER``
    """
    sampled: dict[str, Any] = {
        **sample_optimisation_params(trial),  # batch size from 128 to 1024 (DACER paper: 256)
        "n_diffusion_steps": trial.suggest_categorical("n_diffusion_steps", [5, 10, 20]),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCH)),
        "alpha_learning_rate": trial.suggest_float("alpha_learning_rate", 1e-3, 0.1, log=True),
        "alpha_update_interval": trial.suggest_categorical("alpha_update_interval", [1_000, 5_000, 10_000]),
    }
    trial.set_user_attr("batch_size", 2 ** sampled["batch_size_pow"])
    return convert_dacer_params(sampled, policy_kwargs)


def convert_dsac_params(sampled_params: dict[str, Any], policy_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """
    Turn the values drawn by :func:`sample_dsac_params` (an Optuna trial's ``params``) into DSAC arguments:
    ``batch_size_pow`` and ``net_arch`` as for DACER, ``initial_ent_coef`` into ``ent_coef="auto_<value>"``.

    :param sampled_params: Optuna parameters, as named in :func:`sample_dsac_params`
    :param policy_kwargs: ``policy_kwargs`` of the YAML entry, which the sampled ``net_arch`` updates
    :return: keyword arguments for ``DSAC``
    """
    hyperparams = convert_dacer_params(sampled_params, policy_kwargs)
    if "initial_ent_coef" in hyperparams:
        hyperparams["ent_coef"] = f"auto_{hyperparams.pop('initial_ent_coef')}"
    return hyperparams


def sample_dsac_params(
    trial: optuna.Trial,
    n_actions: int,
    n_envs: int,
    additional_args: dict[str, Any],
    policy_kwargs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """
    Sampler for DSAC hyper-parameters (RL Zoo's ``HYPERPARAMS_SAMPLER`` signature): the optimisation settings, the
    network size, the temperature's start and learning rate, the running-σ coefficient and the critic loss, around
    the authors' values.

    :param trial: Optuna trial
    :param n_actions: action dimension (unused: ``target_entropy="auto"`` already scales with it)
    :param n_envs: number of environments (unused)
    :param additional_args: RL Zoo's extra arguments (unused: no HER replay buffer here)
    :param policy_kwargs: ``policy_kwargs`` of the YAML entry, kept apart from the sampled ``net_arch``
    :return: keyword arguments for ``DSAC``
    """
    sampled: dict[str, Any] = {
        **sample_optimisation_params(trial),  # batch size from 128 to 1024 (authors: 256)
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCH)),
        "initial_ent_coef": trial.suggest_categorical("initial_ent_coef", [0.1, 1.0, 2.718]),  # authors: e
        "alpha_learning_rate": trial.suggest_float("alpha_learning_rate", 3e-5, 3e-3, log=True),
        "tau_b": trial.suggest_float("tau_b", 1e-4, 0.05, log=True),
    }
    trial.set_user_attr("batch_size", 2 ** sampled["batch_size_pow"])
    return convert_dsac_params(sampled, policy_kwargs)


#: Each algorithm's Optuna sampler and its converter (RL Zoo's ``HYPERPARAMS_SAMPLER`` and ``HYPERPARAMS_CONVERTER``)
SAMPLERS = {"dacerf": sample_dacerf_params, "dacer": sample_dacer_params, "dsac": sample_dsac_params}
CONVERTERS = {"dacerf": convert_dacerf_params, "dacer": convert_dacer_params, "dsac": convert_dsac_params}


def default_config(algo: str, env_id: str) -> str | None:
    """
    The YAML file RL Zoo should read when no ``--conf-file`` is given.

    :param algo: RL Zoo algorithm name
    :param env_id: Gymnasium id
    :return: ``hyperparams/<algo>.yml`` for DACERF, DACER and DSAC; ``hyperparams/<algo>.yml`` of
        this package for another algorithm when it has an entry for ``env_id`` (e.g. SAC on ``DMC-*`` ids); else
        ``None`` (RL Zoo's own file)
    """
    path = HYPERPARAMS_DIR / f"{algo}.yml"
    if algo in ALGORITHMS or (path.is_file() and env_id in yaml.safe_load(path.read_text())):
        return str(path)
    return None


#: Environment variable: seconds between the heartbeats of a trial in a database study (0: no heartbeat)
HEARTBEAT_VARIABLE = "SB3_DACERF_OPTUNA_HEARTBEAT"
DEFAULT_HEARTBEAT_INTERVAL = 60


def heartbeat_interval() -> int:
    """Seconds between two heartbeats of a running trial (``SB3_DACERF_OPTUNA_HEARTBEAT``, 60 by default; 0: off)."""
    value = os.environ.get(HEARTBEAT_VARIABLE, str(DEFAULT_HEARTBEAT_INTERVAL))
    try:
        interval = int(value)
    except ValueError:
        interval = -1
    if interval < 0:
        raise ValueError(f"{HEARTBEAT_VARIABLE}={value!r}: give a whole number of seconds (0 turns the heartbeat off).")
    return interval


def is_database_url(storage: object) -> bool:
    """Whether RL Zoo hands ``--storage`` to Optuna as a database URL (``postgresql://...``, ``mysql://...``, ``sqlite:///...``)."""
    return isinstance(storage, str) and "://" in storage and not storage.endswith(".log")


def database_storage(url: str, interval: int, attempts: int = 5) -> optuna.storages.RDBStorage:
    """
    Optuna's storage on a database URL, with the trial heartbeat every ``interval`` seconds (0: none).

    Workers started at the same moment on a new database race to create Optuna's tables, and all but one fail
    (``duplicate key value violates unique constraint``): the storage is opened again after a short random pause,
    when the tables exist.
    """
    import sqlalchemy.exc

    for attempt in range(attempts):
        try:
            return optuna.storages.RDBStorage(url, heartbeat_interval=interval or None)
        except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError):
            if attempt == attempts - 1:
                raise
            time.sleep(random.uniform(0.5, 2.0))
    raise AssertionError("unreachable")


@contextlib.contextmanager
def database_studies(interval: int) -> Iterator[None]:
    """
    Inside the block, a study that ``optuna.create_study`` opens on a database URL goes through
    :func:`database_storage`: workers started together on a new database do not fail, and with ``interval > 0`` every
    running trial records a heartbeat each ``interval`` seconds; whenever a worker starts a trial, trials whose
    heartbeat stopped for ``2 * interval`` seconds (a worker killed or its machine lost) are marked FAIL instead of
    staying RUNNING forever (and counting against ``--max-total-trials``).
    """
    create_study = optuna.create_study

    @functools.wraps(create_study)
    def create_study_on_database(*args: Any, storage: Any = None, **kwargs: Any) -> optuna.Study:
        if is_database_url(storage):
            storage = database_storage(storage, interval)
        return create_study(*args, storage=storage, **kwargs)

    optuna.create_study = create_study_on_database
    try:
        yield
    finally:
        optuna.create_study = create_study


#: The key of a YAML entry's ``normalize`` dict that chooses :class:`~sb3_dacerf.common.vec_normalize.MaskedVecNormalize`
MASKED_KEY = "masked"


def masked_normalization(normalize_kwargs: dict[str, Any]) -> bool:
    """
    Take ``masked`` out of RL Zoo's ``normalize`` arguments (a YAML entry's ``normalize: "dict(norm_obs=True,
    norm_reward=False, masked=True)"``): whether the observations are normalised with
    :class:`~sb3_dacerf.common.vec_normalize.MaskedVecNormalize`, whose empty vehicle rows stay zeros, instead of SB3's
    ``VecNormalize``. The other arguments are both classes' arguments.

    :param normalize_kwargs: RL Zoo's ``normalize_kwargs``, from which ``masked`` is removed
    :return: whether ``masked=True`` was given
    :raises ValueError: ``masked`` that is not ``True`` or ``False``, or ``masked=True`` with ``norm_obs=False``
    """
    masked = normalize_kwargs.pop(MASKED_KEY, False)
    if not isinstance(masked, bool):
        raise ValueError(f"normalize: {MASKED_KEY}={masked!r}: write {MASKED_KEY}=True (MaskedVecNormalize) or leave it out")
    if masked and not normalize_kwargs.get("norm_obs", True):
        raise ValueError(
            f"normalize: {MASKED_KEY}=True normalises the observations' vehicle rows, but norm_obs=False turns observation "
            f"normalisation off: drop norm_obs=False, or {MASKED_KEY}=True"
        )
    return masked


def masked_rows(venv: VecEnv, env_id: str) -> tuple[int, int, int]:
    """
    The table of optional rows of a driving env's observation (``rows`` of
    :class:`~sb3_dacerf.common.vec_normalize.MaskedVecNormalize`): its vehicle rows, from the env's config.

    :param venv: the vectorised env that ``MaskedVecNormalize`` wraps
    :param env_id: its id, for the error message
    :raises ValueError: an env without the driving envs' config
    """
    from sb3_dacerf.envs.driving.common.observation import vehicle_rows  # (highway-env: the driving extra)

    try:
        config = venv.get_attr("config")[0]
        return vehicle_rows(config)
    except (AttributeError, KeyError, TypeError) as error:
        raise ValueError(
            f"normalize: {MASKED_KEY}=True normalises the vehicle rows of a driving env's observation (DACERF-Multilane-v0, "
            f"DACERF-Intersection-v0), but {env_id} has no driving config ({error!r}): drop {MASKED_KEY}=True for it"
        ) from error


_PATCHED_MARK = "_sb3_dacerf_patched"


def _patch_experiment_manager(cls: "type[ExperimentManager]") -> None:
    if getattr(cls, _PATCHED_MARK, False):
        return
    init = cls.__init__
    init_signature = inspect.signature(init)
    optimize = cls.hyperparameters_optimization
    preprocess_normalization, maybe_normalize = cls._preprocess_normalization, cls._maybe_normalize

    @functools.wraps(init)
    def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        if init_signature.bind(self, *args, **kwargs).arguments.get("config") is None:
            self.config = default_config(self.algo, self.env_name.gym_id) or self.config

    @functools.wraps(preprocess_normalization)
    def _preprocess_normalization(self: Any, hyperparams: dict[str, Any]) -> dict[str, Any]:
        hyperparams = preprocess_normalization(self, hyperparams)
        self.normalize_kwargs = dict(self.normalize_kwargs)  # RL Zoo's may be the entry's own dict, which it saves
        self._sb3_dacerf_masked = masked_normalization(self.normalize_kwargs)
        return hyperparams

    @functools.wraps(maybe_normalize)
    def _maybe_normalize(self: Any, env: VecEnv, eval_env: bool) -> VecEnv:
        saved = os.path.join(os.path.dirname(self.trained_agent), self.env_name, "vecnormalize.pkl")
        if not getattr(self, "_sb3_dacerf_masked", False) or os.path.exists(saved):
            return maybe_normalize(self, env, eval_env)  # (saved statistics load as the class that saved them)
        kwargs = self.normalize_kwargs.copy()
        if eval_env:  # as RL Zoo's evaluation env: statistics copied from the training env, rewards as they are
            kwargs.update(norm_reward=False, training=False)
        if self.verbose > 0:
            print(f"Normalization activated: MaskedVecNormalize {kwargs}")
        return MaskedVecNormalize(env, rows=masked_rows(env, self.env_name.gym_id), **kwargs)

    @functools.wraps(optimize)
    def hyperparameters_optimization(self: Any) -> None:
        if self.algo in ALGORITHMS:
            from rl_zoo3.hyperparams_opt import HYPERPARAMS_SAMPLER

            # RL Zoo replaces the YAML's policy_kwargs with the sampled ones: merge instead, to keep the optimizer
            HYPERPARAMS_SAMPLER[self.algo] = functools.partial(
                SAMPLERS[self.algo], policy_kwargs=self._hyperparams.get("policy_kwargs")
            )
        if not is_database_url(self.storage):
            optimize(self)
            return
        with database_studies(heartbeat_interval()):
            optimize(self)

    # Patching RL Zoo's class is what this function is for
    cls.__init__ = __init__  # type: ignore[method-assign]
    cls._preprocess_normalization = _preprocess_normalization  # type: ignore[method-assign]
    cls._maybe_normalize = _maybe_normalize  # type: ignore[method-assign]
    cls.hyperparameters_optimization = hyperparameters_optimization  # type: ignore[method-assign]
    setattr(cls, _PATCHED_MARK, True)


class ParallelTraining:
    """
    What RL Zoo's ``ParallelTrainCallback`` does for an algorithm of this package (:data:`ALGORITHMS`): a copy of
    the model, the *trainer*, takes the gradient steps in a thread while the model collects transitions with the
    latest parameters it received.

    Whenever the trainer is idle at the end of a rollout, its parameters (the policy with ``α``, which lives in the
    actor, the optimizers, any tensor the algorithm saves besides them), its update count and the values it logged
    go to the model; the trainer then gets a copy of the replay buffer and of the ``VecNormalize`` statistics, and the
    model's progress (time steps, so that learning-rate schedules advance), and takes ``gradient_steps`` steps in a
    new thread. The model's own ``train()`` does nothing meanwhile. ``save()`` waits for a running round, then
    writes the trainer (with the model's progress); :meth:`close` waits for the last round and gives the model
    everything back, so that after ``learn()`` it is an ordinary, fully trained model. An error in the thread (e.g. a
    non-finite loss) is raised in the main thread at the next rollout end.

    :param model: The model that ``learn()`` trains, one of this package's algorithms
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
        # Whether the trainer has taken gradient steps since the model last received its parameters
        self.has_news = False
        self._instance_methods = {name: vars(model).get(name) for name in ("train", "save")}
        model.train = _no_gradient_step  # type: ignore[method-assign]
        model.save = self.save  # type: ignore[method-assign]
        self.closed = False

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
        logged.name_to_value.clear()
        logged.name_to_count.clear()
        logged.name_to_excluded.clear()

    def start(self, gradient_steps: int, batch_size: int) -> None:
        """
        Give the idle trainer the replay buffer, the ``VecNormalize`` statistics and the model's progress, and start
        ``gradient_steps`` gradient steps on batches of ``batch_size`` in a thread.
        """
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
        """
        Wait for the last round; give the model the trainer's parameters, and its own ``train()`` and ``save()``
        back (idempotent).
        """
        if self.closed:
            return
        self.closed = True
        for name, method in self._instance_methods.items():
            if method is None:
                vars(self.model).pop(name, None)
            else:
                setattr(self.model, name, method)
        self.wait()
        self.exchange()


def _no_gradient_step(gradient_steps: int, batch_size: int = 64) -> None:
    """``train()`` of a model whose gradient steps a :class:`ParallelTraining` takes in a thread."""


def _parallel_training(callback: Any) -> ParallelTraining | None:
    return vars(callback).get("_sb3_dacerf_parallel_training")


def _patch_parallel_train_callback(cls: "type[ParallelTrainCallback]") -> None:
    """
    Let RL Zoo's ``ParallelTrainCallback`` (``callback: rl_zoo3.callbacks.ParallelTrainCallback`` in a YAML entry or
    ``-params``), which accepts SAC and TQC, train the algorithms of :data:`ALGORITHMS` through
    :class:`ParallelTraining`; it is unchanged for SAC and TQC.
    """
    if getattr(cls, _PATCHED_MARK, False):
        return
    init_callback, on_rollout_end, on_training_end = cls._init_callback, cls._on_rollout_end, cls._on_training_end

    @functools.wraps(init_callback)
    def _init_callback(self: Any) -> None:
        model: OffPolicyAlgorithm = self.model
        if not isinstance(model, tuple(ALGORITHMS.values())):
            init_callback(self)
            return
        training = ParallelTraining(model)
        self._sb3_dacerf_parallel_training = training
        # The attributes RL Zoo's callback reads or offers
        self._model, self.model_class, self.batch_size = training.trainer, type(self.model), training.trainer.batch_size

    @functools.wraps(on_rollout_end)
    def _on_rollout_end(self: Any) -> None:
        training = _parallel_training(self)
        if training is None:
            on_rollout_end(self)
            return
        if training.running:
            return
        training.wait()  # the round that just ended: raise its error, if any
        training.exchange()
        if self.num_timesteps >= training.trainer.learning_starts:
            training.start(self.gradient_steps, self.batch_size)

    @functools.wraps(on_training_end)
    def _on_training_end(self: Any) -> None:
        training = _parallel_training(self)
        if training is None:
            on_training_end(self)
            return
        if self.verbose > 0 and training.running:
            print("Waiting for training thread to terminate")
        training.close()

    # Patching RL Zoo's class is what this function is for
    cls._init_callback = _init_callback  # type: ignore[method-assign]
    cls._on_rollout_end = _on_rollout_end  # type: ignore[method-assign]
    cls._on_training_end = _on_training_end  # type: ignore[method-assign]
    setattr(cls, _PATCHED_MARK, True)


def choose_threads(argv: Sequence[str]) -> None:
    """
    Give PyTorch one thread when the RL Zoo command line ``argv`` trains or runs one of :data:`ALGORITHMS`
    (``--algo``) and does not choose the number itself (``--num-threads``, which RL Zoo then applies). RL Zoo leaves
    PyTorch at its default of one thread per core, and the networks of these algorithms are too small to gain
    from more: on cores that other processes also use, the threads wait for each other.

    :param argv: the script's arguments, as RL Zoo's parser reads them (abbreviations included)
    """
    parser = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    parser.add_argument("--algo")
    parser.add_argument("--num-threads")
    try:
        known, _ = parser.parse_known_args(argv)
    except argparse.ArgumentError:  # RL Zoo's own parser reports it
        return
    if known.algo in ALGORITHMS and known.num_threads is None:
        th.set_num_threads(1)


def register(module: ModuleType) -> None:
    """
    Add DACERF, DACER and DSAC to one RL Zoo module (idempotent): ``rl_zoo3.utils`` (``ALGOS``),
    ``rl_zoo3.hyperparams_opt`` (Optuna samplers and converters), ``rl_zoo3.exp_manager`` (default YAML files) or
    ``rl_zoo3.callbacks`` (``ParallelTrainCallback``, see :class:`ParallelTraining`); other modules are left alone.
    Registering ``rl_zoo3.utils``, which every RL Zoo script imports before it parses its arguments, also chooses
    PyTorch's number of threads from the command line (:func:`choose_threads`).

    :param module: the RL Zoo module, already executed
    """
    if module.__name__ == "rl_zoo3.utils":
        module.ALGOS.update(ALGORITHMS)
        choose_threads(sys.argv[1:])
    elif module.__name__ == "rl_zoo3.hyperparams_opt":
        for algo, sampler in SAMPLERS.items():
            module.HYPERPARAMS_SAMPLER.setdefault(algo, sampler)
        module.HYPERPARAMS_CONVERTER.update(CONVERTERS)
    elif module.__name__ == "rl_zoo3.exp_manager":
        _patch_experiment_manager(module.ExperimentManager)
    elif module.__name__ == "rl_zoo3.callbacks":
        _patch_parallel_train_callback(module.ParallelTrainCallback)


def main() -> None:
    """``python -m sb3_dacerf.zoo <script> [args]``: run ``rl_zoo3.<script>`` (train, enjoy, ...) with DACERF, DACER and DSAC."""
    import rl_zoo3.callbacks
    import rl_zoo3.exp_manager
    import rl_zoo3.hyperparams_opt
    import rl_zoo3.utils

    for module in (rl_zoo3.utils, rl_zoo3.hyperparams_opt, rl_zoo3.exp_manager, rl_zoo3.callbacks):
        register(module)
    if len(sys.argv) < 2:
        raise SystemExit("usage: python -m sb3_dacerf.zoo <train|enjoy|record_video|...> [RL Zoo arguments]")
    script = f"rl_zoo3.{sys.argv[1]}"
    sys.argv = [script, *sys.argv[2:]]
    runpy.run_module(script, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
