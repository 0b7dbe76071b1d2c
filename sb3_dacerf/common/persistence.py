"""
Saving and loading of :class:`~sb3_dacerf.common.twin_critic.TwinCriticAlgorithm` without running code from the file.

A model zip written by ``save`` holds SB3's parts (``data``, the ``.pth`` tensors) and ``sb3_dacerf.json``: the
algorithm, the policy alias, and, as plain JSON, every object SB3 pickles into ``data`` that loading needs (the
spaces, the replay buffer class, ``train_freq``, ``policy_kwargs`` holding classes). ``load`` reads ``data`` as JSON
and never unpickles it: the classes come from closed lists of known names, the tensors are read with
``torch.load(weights_only=True)``. ``load(..., unsafe_run_code_from_file=True)`` is SB3's own load, which unpickles
``data``: a crafted file then runs its code. Observation statistics are saved and loaded as JSON
(:func:`save_vec_normalize`, :func:`load_vec_normalize`).
"""

import hashlib
import importlib
import io
import json
import math
import os
import pathlib
import pickle
import zipfile
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import DictReplayBuffer, NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.preprocessing import check_for_nested_spaces
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.save_util import load_from_zip_file, recursive_setattr
from stable_baselines3.common.torch_layers import CombinedExtractor, FlattenExtractor, NatureCNN
from stable_baselines3.common.type_aliases import GymEnv, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import check_for_correct_spaces, get_system_info
from stable_baselines3.common.vec_env import VecEnv, VecNormalize
from stable_baselines3.common.vec_env.patch_gym import _convert_space

from sb3_dacerf.common.buffers import DemonstrationReplayBuffer
from sb3_dacerf.common.utils import atomic_path, remove_stale_temporaries, save_path_with_suffix
from sb3_dacerf.common.vec_normalize import MaskedRowsRunningMeanStd, MaskedVecNormalize

SelfPersistence = TypeVar("SelfPersistence", bound="TwinCriticPersistence")
SelfAlgorithm = TypeVar("SelfAlgorithm", bound=BaseAlgorithm)

#: The zip entry with the JSON that ``load`` rebuilds SB3's pickled objects from
SAFE_ENTRY = "sb3_dacerf.json"
#: Name of the argument (and ``--unsafe-run-code-from-file`` option) that loads a file by unpickling it
UNSAFE_OPTION = "unsafe_run_code_from_file"

#: Classes a ``policy_kwargs`` value or the replay buffer class may name in ``sb3_dacerf.json``: a closed list
KNOWN_CLASSES: dict[str, type] = {
    f"{cls.__module__}.{cls.__qualname__}": cls
    for cls in (
        *(getattr(th.nn, name) for name in ("ReLU", "Tanh", "ELU", "GELU", "SiLU", "Mish", "LeakyReLU", "Sigmoid", "Softplus")),
        *(getattr(th.optim, name) for name in ("Adam", "AdamW", "SGD", "RMSprop")),
        FlattenExtractor,
        CombinedExtractor,
        NatureCNN,
        ReplayBuffer,
        DictReplayBuffer,
        NStepReplayBuffer,
        DemonstrationReplayBuffer,
    )
}
#: Learning-rate schedule classes ``sb3_dacerf.json`` may name (SB3's and RL Zoo's ``lin_``), with their fields
KNOWN_SCHEDULES = frozenset(
    {
        "stable_baselines3.common.utils.ConstantSchedule",
        "stable_baselines3.common.utils.LinearSchedule",
        "stable_baselines3.common.utils.FloatSchedule",
        "rl_zoo3.utils.SimpleLinearSchedule",
    }
)
#: What ``data`` pickles that a safe load leaves at the constructor's values: the episode statistics (they restart
#: with the next ``learn``) and the schedule ``_setup_model`` rebuilds from
#: ``learning_rate``
RESTARTED_ON_LOAD = frozenset({"ep_info_buffer", "ep_success_buffer", "lr_schedule"})
#: The rollout's last observations, kept as JSON arrays when they are arrays (a ``load(..., force_reset=False)`` goes
#: on from them, as SB3's does) and restarted otherwise
RESUMED_IF_ENCODED = frozenset({"_last_obs", "_last_episode_starts", "_last_original_obs"})


class UnsafeFileError(ValueError):
    """A file cannot be loaded without running code from it (unpickling); the message names what and the ways out."""


class TwinCriticPersistence(OffPolicyAlgorithm):
    """
    Saving and loading of :class:`~sb3_dacerf.common.twin_critic.TwinCriticAlgorithm`, which derives from this class:
    its actor and critics (``policy.actor``, ``policy.critic``, ``policy.critic_target``) are saved as part of the
    policy, with the optimizers of the actor and of the critics. It adds no constructor argument.
    """

    critic: BaseModel

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Any = None,
        include: Any = None,
    ) -> None:
        """
        See :meth:`BaseAlgorithm.save`; the zip also holds ``sb3_dacerf.json``, from which :meth:`load` rebuilds the
        model without unpickling. A file path is written atomically: to a temporary file in the same folder, renamed
        over ``path`` once complete, so a failed or killed save leaves the previous file intact (and the temporary
        file of a killed save is deleted by the next save or load in that folder).
        """
        content = _zip_with_safe_entry(self, lambda buffer: super(TwinCriticPersistence, self).save(buffer, exclude, include))
        if isinstance(path, io.BufferedIOBase):
            path.write(content)
            return
        with atomic_path(save_path_with_suffix(path, "zip")) as temporary:
            temporary.write_bytes(content)

    def save_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase) -> None:
        """
        See :meth:`OffPolicyAlgorithm.save_replay_buffer`; a file path is written atomically, like :meth:`save`.
        """
        if isinstance(path, io.BufferedIOBase):
            super().save_replay_buffer(path)
            return
        with atomic_path(save_path_with_suffix(path, "pkl")) as temporary:
            super().save_replay_buffer(temporary)

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """
        See :meth:`OffPolicyAlgorithm.load_replay_buffer` (a pickle: load only replay buffers you saved). A buffer of
        observations or actions of other spaces than the model's (another environment's) is refused with both, and
        the model keeps its buffer.
        """
        previous = self.replay_buffer
        super().load_replay_buffer(path, truncate_last_traj)
        buffer = self.replay_buffer
        assert buffer is not None
        for name in ("observation_space", "action_space"):
            theirs, ours = getattr(buffer, name), getattr(self, name)
            if theirs != ours:
                self.replay_buffer = previous  # the model keeps its own buffer
                raise ValueError(
                    f"The replay buffer in {path} holds transitions of the {name} {theirs}, the model's is {ours}: "
                    "load the buffer saved with this model (another environment's transitions cannot be trained on)."
                )

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfPersistence],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        unsafe_run_code_from_file: bool = False,
        **kwargs: Any,
    ) -> SelfPersistence:
        """
        Load a model saved by ``save``, running no code from the file: see :meth:`BaseAlgorithm.load` for the
        arguments. ``data`` is read as JSON, the objects SB3 pickles are rebuilt from ``sb3_dacerf.json`` and closed
        lists of known classes, the tensors are read with ``torch.load(weights_only=True)``. The last rollout's
        observations come back (``force_reset=False`` goes on from them); the episode statistics restart with the next
        ``learn``.

        :param custom_objects: Values of ``data`` entries to use instead of the file's (e.g. a learning-rate schedule,
            which a file holds only pickled): ``{"learning_rate": 0.0}`` to load such a model for prediction
        :param unsafe_run_code_from_file: Load with SB3's ``load``, which unpickles the file's objects: a crafted
            file runs any code it holds, with your permissions. Only for files you made or trust, e.g. a model whose
            ``policy_kwargs`` hold a class of your own
        :raises ValueError: a file of another algorithm (naming it), a zip missing parts (naming them), or, as
            :class:`UnsafeFileError`, a file holding pickled objects a safe load cannot rebuild (naming them)
        """
        return safe_load(
            cls, path, env, device, custom_objects, print_system_info, force_reset, unsafe_run_code_from_file, **kwargs
        )

    def set_parameters(
        self,
        load_path_or_dict: str | pathlib.Path | io.BufferedIOBase | dict[str, Any],
        exact_match: bool = True,
        device: th.device | str = "auto",
    ) -> None:
        """
        See :meth:`BaseAlgorithm.set_parameters`: from a file, only the tensors are read, with
        ``torch.load(weights_only=True)``; ``data`` is not read.
        """
        if not isinstance(load_path_or_dict, dict):
            if isinstance(load_path_or_dict, (str, os.PathLike)):
                load_path_or_dict = _existing_zip(load_path_or_dict)
            load_path_or_dict = read_tensors(load_path_or_dict, device)[0]
        super().set_parameters(load_path_or_dict, exact_match=exact_match, device=device)  # type: ignore[arg-type]

    def _excluded_save_params(self) -> list[str]:
        return super()._excluded_save_params() + ["actor", "critic", "critic_target"]  # noqa: RUF005

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        return state_dicts, []


def _zip_with_safe_entry(model: BaseAlgorithm, save: Callable[[io.BytesIO], None]) -> bytes:
    """The zip ``save`` writes for ``model``, with :data:`SAFE_ENTRY` added."""
    with io.BytesIO() as buffer:
        save(buffer)
        with zipfile.ZipFile(buffer, "a") as archive:
            archive.writestr(SAFE_ENTRY, json.dumps(_safe_entry(model, json.loads(archive.read("data")))))
        return buffer.getvalue()


def safe_save(model: BaseAlgorithm, path: str | pathlib.Path) -> None:
    """
    Save any SB3 algorithm (e.g. ``SAC``) as ``model.save(path)`` does, atomically, with ``sb3_dacerf.json``, so that
    :func:`safe_load` reads it back without running code from the file. This package's algorithms do so in ``save``.
    """
    if isinstance(model, TwinCriticPersistence):
        model.save(path)
        return
    content = _zip_with_safe_entry(model, lambda buffer: model.save(buffer))  # type: ignore[arg-type]
    with atomic_path(save_path_with_suffix(path, "zip")) as temporary:
        temporary.write_bytes(content)


def _safe_entry(model: BaseAlgorithm, data: dict[str, Any]) -> dict[str, Any]:
    """The JSON of :data:`SAFE_ENTRY`: what ``data`` pickled, as plain values, and what it could not encode."""
    aliases = [alias for alias, policy in model.policy_aliases.items() if type(model.policy) is policy]
    objects, not_encoded = {}, {}
    for key, value in data.items():
        if not (isinstance(value, dict) and ":serialized:" in value) or key in RESTARTED_ON_LOAD or key == "policy_class":
            continue
        try:
            objects[key] = _encode(key, getattr(model, key))
        except TypeError as error:
            if key not in RESUMED_IF_ENCODED:
                not_encoded[key] = str(error)
    return {
        "algorithm": type(model).__name__,
        "policy": aliases[0] if aliases else None,
        "objects": objects,
        "not_encoded": not_encoded,
    }


def safe_load(
    cls: type[SelfAlgorithm],
    path: str | pathlib.Path | io.BufferedIOBase,
    env: GymEnv | None = None,
    device: th.device | str = "auto",
    custom_objects: dict[str, Any] | None = None,
    print_system_info: bool = False,
    force_reset: bool = True,
    unsafe_run_code_from_file: bool = False,
    **kwargs: Any,
) -> SelfAlgorithm:
    """
    ``cls.load(path, ...)`` for any SB3 algorithm (``SAC`` as well as this package's, whose ``load`` is this function),
    running no code from the file: see :meth:`TwinCriticPersistence.load`. The file must hold ``sb3_dacerf.json``
    (written by this package's ``save`` or by :func:`safe_save`).
    """
    if isinstance(path, (str, os.PathLike)):
        path = _existing_zip(path)
        remove_stale_temporaries(path)
    entry, data = _read_json_parts(path)
    _check_algorithm(cls, path, entry)
    if unsafe_run_code_from_file:
        return BaseAlgorithm.load.__func__(cls, path, env, device, custom_objects, print_system_info, force_reset, **kwargs)  # type: ignore[attr-defined]
    if entry is None:
        raise UnsafeFileError(
            f"{path} has no {SAFE_ENTRY} (it was not saved by this package's save or safe_save), so its spaces "
            f"and classes exist only as pickles. If you trust the file, load it with "
            f"{UNSAFE_OPTION}=True, which runs any code the file holds."
        )
    if entry.get("policy") not in cls.policy_aliases:
        raise UnsafeFileError(
            f"{path} holds a policy that is none of {cls.__name__}'s {list(cls.policy_aliases)}: a safe load cannot "
            f"rebuild it. If you trust the file, load it with {UNSAFE_OPTION}=True, which runs any code it holds."
        )
    data = _rebuilt_data(cls, path, entry, data, {**(custom_objects or {}), **kwargs})
    if print_system_info:
        print("== CURRENT SYSTEM INFO ==")
        get_system_info()
    params, pytorch_variables = read_tensors(path, device)
    if "device" in data["policy_kwargs"]:
        del data["policy_kwargs"]["device"]
    if "policy_kwargs" in kwargs and kwargs["policy_kwargs"] != data["policy_kwargs"]:
        raise ValueError(
            f"The policy_kwargs given ({kwargs['policy_kwargs']}) differ from the saved ones ({data['policy_kwargs']})"
        )
    if env is not None:
        env = cls._wrap_env(env, data["verbose"])
        check_for_correct_spaces(env, data["observation_space"], data["action_space"])
        if force_reset:
            data["_last_obs"] = None
        data["n_envs"] = env.num_envs
    model = cls(policy=cls.policy_aliases[entry["policy"]], env=env, device=device, _init_setup_model=False)  # type: ignore[call-arg,arg-type]
    model.__dict__.update(data)
    model.__dict__.update(kwargs)
    model._setup_model()
    missing = [f"{name}.pth" for name in model._get_torch_save_params()[0] if name not in (params or {})]
    if missing:
        raise ValueError(
            f"{path} is missing {', '.join(missing)} (the {'weights' if 'policy.pth' in missing else 'optimizer state'} "
            f"of the model): it is not a complete file written by {cls.__name__}.save; save the model again."
        )
    model.set_parameters(params, exact_match=True, device=device)  # type: ignore[arg-type]
    for name, value in (pytorch_variables or {}).items():
        if value is not None:
            recursive_setattr(model, f"{name}.data", value.data)
    if model.use_sde:
        model.policy.reset_noise()  # type: ignore[operator]
    return model


def read_tensors(
    path: pathlib.Path | io.BufferedIOBase, device: th.device | str = "auto"
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """
    The state dicts (``policy``, the optimizers) and PyTorch variables of a model zip, read with
    ``torch.load(weights_only=True)``, as SB3's ``set_parameters`` reads them.

    :raises UnsafeFileError: a ``.pth`` part holds objects other than tensors and plain containers
    """
    try:
        _, params, pytorch_variables = load_from_zip_file(path, load_data=False, device=device)
    except pickle.UnpicklingError as error:
        raise UnsafeFileError(
            f"{path} holds weights with objects other than tensors, which torch.load(weights_only=True) refuses to "
            f"unpickle ({str(error).splitlines()[-1][:200]}). If you trust the file, load it with "
            f"{UNSAFE_OPTION}=True, which runs any code it holds."
        ) from None
    return params, pytorch_variables


def _existing_zip(path: str | os.PathLike) -> pathlib.Path:
    """``path``, or ``path.zip`` when only that exists (as SB3 looks it up)."""
    path = pathlib.Path(path)
    if not path.is_file() and pathlib.Path(f"{path}.zip").is_file():
        return pathlib.Path(f"{path}.zip")
    if not path.is_file():
        raise FileNotFoundError(f"No model file at {path} (nor {path}.zip)")
    return path


def _read_json_parts(path: pathlib.Path | io.BufferedIOBase) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """``sb3_dacerf.json`` (``None`` when absent) and ``data`` of a model zip, as JSON; never unpickles."""
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            missing = [name for name in ("data", "policy.pth") if name not in names]
            if missing:
                raise ValueError(
                    f"{path} is missing {' and '.join(missing)} (the model's settings and weights): it is not a complete "
                    "file written by model.save(); save the model again."
                )
            data = json.loads(archive.read("data"))
            entry = json.loads(archive.read(SAFE_ENTRY)) if SAFE_ENTRY in names else None
    except zipfile.BadZipFile:
        raise ValueError(f"{path} wasn't a zip-file: load a model written by model.save()") from None
    if isinstance(path, io.BufferedIOBase):
        path.seek(0)
    if not isinstance(data, dict) or (entry is not None and not isinstance(entry, dict)):
        raise ValueError(f"{path} holds a malformed data or {SAFE_ENTRY} entry: load a model written by model.save()")
    return entry, data


def saved_algorithm_name(path: str | os.PathLike | io.BufferedIOBase) -> str | None:
    """
    The lower-case name of the algorithm a model zip was saved by, read as JSON (never unpickled): ``dacerf`` from
    ``sb3_dacerf.json``, else from the module of the saved policy class (``sac`` for ``stable_baselines3.sac.policies``,
    ``tqc`` for sb3_contrib's); ``None`` when neither names one.
    """
    try:
        entry, data = _read_json_parts(_existing_zip(path) if isinstance(path, (str, os.PathLike)) else path)
    except (OSError, ValueError):
        return None
    if entry is not None and isinstance(entry.get("algorithm"), str):
        return entry["algorithm"].lower()
    policy_class = data.get("policy_class")
    module = policy_class.get("__module__") if isinstance(policy_class, dict) else None
    parts = module.split(".") if isinstance(module, str) else []
    if len(parts) >= 3 and parts[0] in ("stable_baselines3", "sb3_contrib", "sb3_dacerf") and parts[-1] == "policies":
        return parts[1]
    return None


def _check_algorithm(cls: type, path: Any, entry: dict[str, Any] | None) -> None:
    algorithm = saved_algorithm_name(path) if entry is None else str(entry.get("algorithm", "")).lower()
    if algorithm and algorithm != cls.__name__.lower():
        raise ValueError(
            f"{path} holds a {algorithm.upper()} model (as its {'sb3_dacerf.json' if entry else 'saved policy class'} records), "
            f"not a {cls.__name__} model: load it with {algorithm.upper()}.load(...)."
        )


def _rebuilt_data(cls: type, path: Any, entry: dict[str, Any], data: dict[str, Any], given: dict[str, Any]) -> dict[str, Any]:
    """``data`` with its pickled entries replaced: by ``given``, by ``sb3_dacerf.json``'s, or left out to restart."""
    objects, not_encoded = entry.get("objects", {}), entry.get("not_encoded", {})
    rebuilt, unsafe = {}, {}
    for key, value in data.items():
        if key in given:
            rebuilt[key] = given[key]
        elif not (isinstance(value, dict) and ":serialized:" in value):
            rebuilt[key] = value
        elif key == "policy_class":
            continue  # the class of entry["policy"], one of the algorithm's aliases
        elif key in objects:
            rebuilt[key] = _decode(key, objects[key])
        elif key not in RESTARTED_ON_LOAD | RESUMED_IF_ENCODED:
            unsafe[key] = not_encoded.get(key, value.get(":type:", "a pickled object"))
    if unsafe:
        listing = "; ".join(f"{key} ({why})" for key, why in unsafe.items())
        raise UnsafeFileError(
            f"{path} holds objects that exist only as pickles: {listing}. Pass their values with "
            f"custom_objects={{{', '.join(repr(key) + ': ...' for key in unsafe)}}} (e.g. 'learning_rate': 0.0 to "
            f"predict only), or, if you trust the file, load it with {UNSAFE_OPTION}=True, which runs any code it holds."
        )
    for key in ("observation_space", "action_space", "policy_kwargs"):
        if key not in rebuilt:
            raise ValueError(f"{path} has no {key} in its data: it is not a complete file written by {cls.__name__}.save")
    rebuilt["observation_space"] = _convert_space(rebuilt["observation_space"])
    rebuilt["action_space"] = _convert_space(rebuilt["action_space"])
    return rebuilt


def _encode(key: str, value: Any) -> Any:
    """A pickled ``data`` value as JSON for ``sb3_dacerf.json``; ``TypeError`` naming what cannot be encoded."""
    if isinstance(value, spaces.Space):
        return space_to_json(value)
    if isinstance(value, TrainFreq):
        return [int(value.frequency), value.unit.value]
    return _encode_value(value, key)


def _encode_value(value: Any, where: str) -> Any:
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else {"float": str(value)}
    if isinstance(value, (list, tuple)):
        return [_encode_value(item, f"{where}[{i}]") for i, item in enumerate(value)]
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        return {"dict": {k: _encode_value(v, f"{where}[{k!r}]") for k, v in value.items()}}
    if isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
        return {"array": {"dtype": str(value.dtype), "shape": list(value.shape), "data": value.ravel().tolist()}}
    if isinstance(value, type) and f"{value.__module__}.{value.__qualname__}" in KNOWN_CLASSES:
        return {"class": f"{value.__module__}.{value.__qualname__}"}
    schedule = f"{type(value).__module__}.{type(value).__qualname__}"
    if schedule in KNOWN_SCHEDULES:
        return {"schedule": schedule, "fields": {k: _encode_value(v, f"{where}.{k}") for k, v in vars(value).items()}}
    raise TypeError(f"{where} is a {type(value).__name__} ({value!r:.80}), which is none of the known classes")


def _decode(key: str, value: Any) -> Any:
    if key in ("observation_space", "action_space"):
        return space_from_json(value)
    if key == "train_freq":
        return TrainFreq(int(value[0]), TrainFrequencyUnit(value[1]))
    return _decode_value(value)


def _decode_value(value: Any) -> Any:
    if isinstance(value, list):
        return [_decode_value(item) for item in value]
    if isinstance(value, dict):
        if "class" in value:
            if value["class"] not in KNOWN_CLASSES:
                raise UnsafeFileError(f"The file names the class {value['class']!r}, which is none of {sorted(KNOWN_CLASSES)}")
            return KNOWN_CLASSES[value["class"]]
        if "float" in value:
            return float(value["float"])
        if "array" in value:
            array = value["array"]
            dtype = np.dtype(str(array["dtype"]))
            if dtype.kind not in "biuf":
                raise UnsafeFileError(f"The file holds an array of dtype {dtype}: only booleans and numbers are read")
            return np.asarray(array["data"], dtype=dtype).reshape(array["shape"])
        if "schedule" in value:
            if value["schedule"] not in KNOWN_SCHEDULES:
                raise UnsafeFileError(f"The file names the schedule {value['schedule']!r}, none of {sorted(KNOWN_SCHEDULES)}")
            module, _, name = value["schedule"].rpartition(".")
            schedule = object.__new__(getattr(importlib.import_module(module), name))
            schedule.__dict__.update({k: _decode_value(v) for k, v in value["fields"].items()})  # what unpickling does
            return schedule
        return {k: _decode_value(v) for k, v in value["dict"].items()}
    return value


def space_to_json(space: spaces.Space) -> dict[str, Any]:
    """A Box, Discrete, MultiDiscrete, MultiBinary or Dict space as JSON (:func:`space_from_json` reads it back)."""
    if isinstance(space, spaces.Box):
        return {
            "Box": {
                "low": np.asarray(space.low, dtype=np.float64).tolist(),
                "high": np.asarray(space.high, dtype=np.float64).tolist(),
                "shape": list(space.shape),
                "dtype": str(space.dtype),
            }
        }
    if isinstance(space, spaces.Discrete):
        return {"Discrete": {"n": int(space.n), "start": int(space.start)}}
    if isinstance(space, spaces.MultiDiscrete):
        return {"MultiDiscrete": {"nvec": space.nvec.tolist(), "start": space.start.tolist(), "dtype": str(space.dtype)}}
    if isinstance(space, spaces.MultiBinary):
        return {"MultiBinary": {"n": np.asarray(space.n).tolist()}}
    if isinstance(space, spaces.Dict):
        check_for_nested_spaces(space)
        return {"Dict": {key: space_to_json(subspace) for key, subspace in space.spaces.items()}}
    raise TypeError(f"the space {space} is none of Box, Discrete, MultiDiscrete, MultiBinary and Dict")


_DTYPES = frozenset({"float16", "float32", "float64", "uint8", "int8", "int16", "int32", "int64", "bool"})


def space_from_json(description: dict[str, Any]) -> spaces.Space:
    """The space :func:`space_to_json` described; ``ValueError`` for anything else."""
    try:
        ((kind, fields),) = description.items()
        if kind == "Box" and fields["dtype"] in _DTYPES:
            low = np.asarray(fields["low"], dtype=np.float64)
            high = np.asarray(fields["high"], dtype=np.float64)
            return spaces.Box(low.astype(fields["dtype"]), high.astype(fields["dtype"]), tuple(fields["shape"]), fields["dtype"])
        if kind == "Discrete":
            return spaces.Discrete(int(fields["n"]), start=int(fields["start"]))
        if kind == "MultiDiscrete" and fields["dtype"] in _DTYPES:
            return spaces.MultiDiscrete(np.asarray(fields["nvec"]), dtype=fields["dtype"], start=np.asarray(fields["start"]))
        if kind == "MultiBinary":
            return spaces.MultiBinary(fields["n"])
        if kind == "Dict":
            return spaces.Dict({key: space_from_json(value) for key, value in fields.items()})
    except (AttributeError, KeyError, TypeError, ValueError) as error:
        raise ValueError(f"Malformed space description {description!r:.200}: {error}") from None
    raise ValueError(f"Unknown space description {description!r:.200}: Box, Discrete, MultiDiscrete, MultiBinary or Dict")


# Observation statistics (VecNormalize, MaskedVecNormalize) as JSON


def _rms_to_json(rms: RunningMeanStd) -> dict[str, Any]:
    encoded: dict[str, Any] = {"mean": rms.mean.tolist(), "var": rms.var.tolist(), "count": float(rms.count)}
    if isinstance(rms, MaskedRowsRunningMeanStd):
        encoded["rows"] = list(rms.rows)
        encoded["row_rms"] = _rms_to_json(rms.row_rms)
    return encoded


def _rms_from_json(encoded: dict[str, Any]) -> RunningMeanStd:
    mean, var = np.asarray(encoded["mean"], dtype=np.float64), np.asarray(encoded["var"], dtype=np.float64)
    if mean.shape != var.shape:
        raise ValueError(f"mean and var of different shapes {mean.shape} and {var.shape}")
    rms: RunningMeanStd
    if "rows" in encoded:
        rms = MaskedRowsRunningMeanStd(mean.shape, tuple(int(v) for v in encoded["rows"]))  # type: ignore[arg-type]
        rms.row_rms = _rms_from_json(encoded["row_rms"])
    else:
        rms = RunningMeanStd(shape=mean.shape)
    rms.mean, rms.var, rms.count = mean, var, float(encoded["count"])
    return rms


def vec_normalize_to_json(vec_normalize: VecNormalize) -> dict[str, Any]:
    """The statistics and settings of a ``VecNormalize`` (or ``MaskedVecNormalize``) as JSON."""
    obs_rms = vec_normalize.obs_rms
    return {
        "class": "MaskedVecNormalize" if isinstance(vec_normalize, MaskedVecNormalize) else "VecNormalize",
        "observation_space": space_to_json(vec_normalize.observation_space),
        "action_space": space_to_json(vec_normalize.action_space),
        "norm_obs": bool(vec_normalize.norm_obs),
        "norm_reward": bool(vec_normalize.norm_reward),
        "norm_obs_keys": vec_normalize.norm_obs_keys,
        "clip_obs": float(vec_normalize.clip_obs),
        "clip_reward": float(vec_normalize.clip_reward),
        "gamma": float(vec_normalize.gamma),
        "epsilon": float(vec_normalize.epsilon),
        "training": bool(vec_normalize.training),
        "rows": list(vec_normalize.rows) if isinstance(vec_normalize, MaskedVecNormalize) else None,
        "obs_rms": {"dict": {key: _rms_to_json(rms) for key, rms in obs_rms.items()}}
        if isinstance(obs_rms, dict)
        else _rms_to_json(obs_rms),
        "ret_rms": _rms_to_json(vec_normalize.ret_rms),
    }


def save_vec_normalize(vec_normalize: VecNormalize, path: str | os.PathLike) -> None:
    """Write a ``VecNormalize``'s statistics and settings as JSON, atomically; :func:`load_vec_normalize` reads them."""
    with atomic_path(path) as temporary:
        temporary.write_text(json.dumps(vec_normalize_to_json(vec_normalize)))


def load_vec_normalize(path: str | os.PathLike, venv: VecEnv | None = None) -> VecNormalize:
    """
    The ``VecNormalize`` (or ``MaskedVecNormalize``) of statistics written by :func:`save_vec_normalize`, wrapping
    ``venv`` if given (as ``VecNormalize.load`` does); without ``venv`` it normalises observations
    (``normalize_obs``) and can be exported, but not stepped. Reads JSON only.

    :raises ValueError: a file that is not such JSON, or ``venv``'s spaces differ from the statistics'
    """
    try:
        encoded = json.loads(pathlib.Path(path).read_text())
        classes: dict[str, type[VecNormalize]] = {"VecNormalize": VecNormalize, "MaskedVecNormalize": MaskedVecNormalize}
        cls = classes[encoded["class"]]
        obs_rms = encoded["obs_rms"]
        state = {
            "observation_space": space_from_json(encoded["observation_space"]),
            "action_space": space_from_json(encoded["action_space"]),
            "norm_obs": bool(encoded["norm_obs"]),
            "norm_reward": bool(encoded["norm_reward"]),
            "norm_obs_keys": encoded["norm_obs_keys"],
            "clip_obs": float(encoded["clip_obs"]),
            "clip_reward": float(encoded["clip_reward"]),
            "gamma": float(encoded["gamma"]),
            "epsilon": float(encoded["epsilon"]),
            "training": bool(encoded["training"]),
            "obs_rms": {key: _rms_from_json(rms) for key, rms in obs_rms["dict"].items()}
            if "dict" in obs_rms
            else _rms_from_json(obs_rms),
            "ret_rms": _rms_from_json(encoded["ret_rms"]),
            "num_envs": 1,
            "render_mode": None,
            "metadata": {},
            "reset_infos": [{}],
            "_seeds": [None],
            "_options": [{}],
            "old_obs": np.array([]),
            "old_reward": np.array([]),
            "returns": np.zeros(1),
        }
        if cls is MaskedVecNormalize:
            state["rows"] = tuple(int(v) for v in encoded["rows"])
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as error:
        raise ValueError(
            f"{path} is not observation statistics written by sb3_dacerf's save_vec_normalize (JSON): "
            f"{type(error).__name__}: {error}"
        ) from None
    normalizer: VecNormalize = object.__new__(cls)
    normalizer.__setstate__(state)  # what unpickling does, from the JSON's values
    if venv is not None:
        normalizer.set_venv(venv)
        n_envs = venv.num_envs
        normalizer.reset_infos, normalizer._seeds, normalizer._options = (
            [{} for _ in range(n_envs)],
            [None] * n_envs,
            [{}] * n_envs,
        )
    return normalizer


# Checksums of shipped files


#: The checksum file of a folder of shipped models, in ``sha256sum``'s format (``<hex digest>  <file name>``)
CHECKSUMS = "SHA256SUMS"


def sha256(path: str | os.PathLike) -> str:
    """The hex sha256 digest of a file."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_sha256sums(folder: str | os.PathLike) -> dict[str, str]:
    """The ``SHA256SUMS`` of a folder as ``{file name: hex digest}``; empty when the folder has none."""
    path = pathlib.Path(folder) / CHECKSUMS
    if not path.is_file():
        return {}
    sums = {}
    for line in path.read_text().splitlines():
        digest, _, name = line.strip().partition("  ")
        if name:
            sums[name.lstrip("*")] = digest.lower()
    return sums


def check_sha256(path: str | os.PathLike) -> None:
    """
    Check a file against the ``SHA256SUMS`` of its folder, if that lists it (the shipped drivers of
    ``examples/models/``); a file no ``SHA256SUMS`` lists is not checked.

    :raises ValueError: the file's digest differs from the listed one, naming both
    """
    path = pathlib.Path(path)
    expected = read_sha256sums(path.parent).get(path.name)
    if expected is None:
        return
    actual = sha256(path)
    if actual != expected:
        raise ValueError(
            f"{path} does not match its checksum in {path.parent / CHECKSUMS} (sha256 {actual}, listed {expected}): "
            "the file was changed or corrupted; download it again (or, for a file you changed yourself, update "
            f"{CHECKSUMS} with `sha256sum`)."
        )


def update_sha256sums(paths: list[str | os.PathLike]) -> None:
    """Write the digests of ``paths`` into the ``SHA256SUMS`` of their folder, which must exist (others are kept)."""
    for folder, names in _by_folder(paths).items():
        sums = read_sha256sums(folder)
        sums.update({name: sha256(folder / name) for name in names})
        with atomic_path(folder / CHECKSUMS) as temporary:
            temporary.write_text("".join(f"{digest}  {name}\n" for name, digest in sorted(sums.items())))


def _by_folder(paths: list[str | os.PathLike]) -> dict[pathlib.Path, list[str]]:
    folders: dict[pathlib.Path, list[str]] = {}
    for path in map(pathlib.Path, paths):
        folders.setdefault(path.parent, []).append(path.name)
    return folders


__all__ = [
    "CHECKSUMS",
    "KNOWN_CLASSES",
    "SAFE_ENTRY",
    "UNSAFE_OPTION",
    "TwinCriticPersistence",
    "UnsafeFileError",
    "check_sha256",
    "load_vec_normalize",
    "read_sha256sums",
    "safe_load",
    "safe_save",
    "save_vec_normalize",
    "saved_algorithm_name",
    "sha256",
    "space_from_json",
    "space_to_json",
    "update_sha256sums",
    "vec_normalize_to_json",
]
