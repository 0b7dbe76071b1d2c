"""
Saving and loading without running code from the file. A zip written by ``save`` (or :func:`safe_save`) holds SB3's
parts and ``sb3_dacerf.json``: the algorithm, the policy alias and, as plain JSON, the objects SB3 pickles into
``data``. ``load`` (:func:`safe_load`) rebuilds them from closed lists of known classes and reads the tensors with
``torch.load(weights_only=True)``. Also: observation statistics as JSON, ``SHA256SUMS`` checks of shipped files.
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

from sb3_dacerf.common.utils import atomic_path, remove_stale_temporaries, save_path_with_suffix
from sb3_dacerf.common.vec_normalize import MaskedRowsRunningMeanStd, MaskedVecNormalize

SelfAlgorithm = TypeVar("SelfAlgorithm", bound=BaseAlgorithm)
ZipPath = str | pathlib.Path | io.BufferedIOBase

#: The zip entry with the JSON that ``load`` rebuilds SB3's pickled objects from
SAFE_ENTRY = "sb3_dacerf.json"
_IF_TRUSTED = "If you trust the file, load it with unsafe_run_code_from_file=True, which runs any code it holds."

#: Classes a ``policy_kwargs`` value or the replay buffer class may name in ``sb3_dacerf.json``: a closed list
KNOWN_CLASSES: dict[str, type] = {
    f"{cls.__module__}.{cls.__qualname__}": cls
    for cls in (
        *(getattr(th.nn, name) for name in ("ReLU", "Tanh", "ELU", "GELU", "SiLU", "Mish", "LeakyReLU", "Sigmoid", "Softplus")),
        *(getattr(th.optim, name) for name in ("Adam", "AdamW", "SGD", "RMSprop")),
        *(FlattenExtractor, CombinedExtractor, NatureCNN),
        *(ReplayBuffer, DictReplayBuffer, NStepReplayBuffer),
    )
}
# Learning-rate schedules (SB3's and RL Zoo's lin_) stored as their class and fields
_SCHEDULES = frozenset(
    f"stable_baselines3.common.utils.{name}" for name in ("ConstantSchedule", "LinearSchedule", "FloatSchedule")
) | {"rl_zoo3.utils.SimpleLinearSchedule"}
# Pickled in data, left at the constructor's values: episode statistics, the schedule _setup_model rebuilds
_RESTARTED = frozenset({"ep_info_buffer", "ep_success_buffer", "lr_schedule"})
# The rollout's last observations: stored when arrays (force_reset=False goes on from them), restarted otherwise
_RESUMED = frozenset({"_last_obs", "_last_episode_starts", "_last_original_obs"})


class UnsafeFileError(ValueError):
    """A file cannot be loaded without running code from it (unpickling); the message names what and the ways out."""


def safe_load(
    cls: type[SelfAlgorithm],
    path: ZipPath,
    env: GymEnv | None = None,
    device: th.device | str = "auto",
    custom_objects: dict[str, Any] | None = None,
    print_system_info: bool = False,
    force_reset: bool = True,
    unsafe_run_code_from_file: bool = False,
    **kwargs: Any,
) -> SelfAlgorithm:
    """
    ``cls.load(path, ...)`` (see :meth:`BaseAlgorithm.load`) running no code from the file: the ``load`` of this
    package's algorithms, and for other SB3 algorithms ``safe_load(SAC, path)`` of a file written by :func:`safe_save`.
    The last rollout's observations come back (``force_reset=False`` goes on from them); the episode statistics
    restart with the next ``learn``.

    :param custom_objects: Values of ``data`` entries to use instead of the file's, e.g. ``{"learning_rate": 0.0}``
        for a learning-rate schedule the file holds only pickled
    :param unsafe_run_code_from_file: Load with SB3's ``load``, which unpickles: a crafted file runs any code it
        holds. Only for files you made or trust (e.g. ``policy_kwargs`` holding a class of your own)
    :raises ValueError: a file of another algorithm, a zip missing parts (naming them), or, as
        :class:`UnsafeFileError`, a file holding pickled objects a safe load cannot rebuild (naming them)
    """
    path = _zip_path(path)
    if not isinstance(path, io.BufferedIOBase):
        remove_stale_temporaries(path)
    entry, data = _read_json_parts(path)
    algorithm = _algorithm_name(entry, data)
    if algorithm and algorithm != cls.__name__.lower():
        raise ValueError(
            f"{path} holds a {algorithm.upper()} model (as its {SAFE_ENTRY if entry else 'saved policy class'} records), "
            f"not a {cls.__name__} model: load it with {algorithm.upper()}.load(...)."
        )
    if unsafe_run_code_from_file:
        return BaseAlgorithm.load.__func__(cls, path, env, device, custom_objects, print_system_info, force_reset, **kwargs)  # type: ignore[attr-defined]
    if entry is None:
        raise UnsafeFileError(
            f"{path} has no {SAFE_ENTRY} (it was not saved by this package's save or safe_save), so its spaces "
            f"and classes exist only as pickles. {_IF_TRUSTED}"
        )
    if entry.get("policy") not in cls.policy_aliases:
        raise UnsafeFileError(
            f"{path} holds a policy that is none of {cls.__name__}'s {list(cls.policy_aliases)}: a safe load cannot "
            f"rebuild it. {_IF_TRUSTED}"
        )
    data = _rebuilt_data(cls, path, entry, data, {**(custom_objects or {}), **kwargs})
    if print_system_info:
        print("== CURRENT SYSTEM INFO ==")
        get_system_info()
    params, pytorch_variables = _read_tensors(path, device)
    data["policy_kwargs"].pop("device", None)
    if env is not None:
        env = cls._wrap_env(env, data["verbose"])
        check_for_correct_spaces(env, data["observation_space"], data["action_space"])
        if force_reset:
            data["_last_obs"] = None
        data["n_envs"] = env.num_envs
    model = cls(policy=cls.policy_aliases[entry["policy"]], env=env, device=device, _init_setup_model=False)  # type: ignore[call-arg,arg-type]
    model.__dict__.update({**data, **kwargs})
    model._setup_model()
    missing = [f"{name}.pth" for name in model._get_torch_save_params()[0] if name not in params]
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


class TwinCriticPersistence(OffPolicyAlgorithm):
    """Saving and loading of :class:`~sb3_dacerf.common.twin_critic.TwinCriticAlgorithm` (a subclass): the policy,
    with the optimizers of the actor and of the critics."""

    critic: BaseModel

    @classmethod
    def load(cls: type[SelfAlgorithm], path: ZipPath, *args: Any, **kwargs: Any) -> SelfAlgorithm:  # type: ignore[override]
        """:func:`safe_load` into this class (the same arguments): loads a model without running code from the file."""
        return safe_load(cls, path, *args, **kwargs)

    def save(self, path: ZipPath, exclude: Any = None, include: Any = None) -> None:
        """See :meth:`BaseAlgorithm.save`, with ``sb3_dacerf.json`` in the zip; a file path is written atomically (a
        temporary file renamed over ``path`` once complete; the next save or load deletes that of a killed save)."""
        _save_with_entry(self, path, lambda buffer: super(TwinCriticPersistence, self).save(buffer, exclude, include))

    def save_replay_buffer(self, path: ZipPath) -> None:
        """See :meth:`OffPolicyAlgorithm.save_replay_buffer`; a file path is written atomically, like :meth:`save`."""
        if isinstance(path, io.BufferedIOBase):
            super().save_replay_buffer(path)
            return
        with atomic_path(save_path_with_suffix(path, "pkl")) as temporary:
            super().save_replay_buffer(temporary)

    def load_replay_buffer(self, path: ZipPath, truncate_last_traj: bool = True) -> None:
        """See :meth:`OffPolicyAlgorithm.load_replay_buffer` (a pickle: load only your own); a buffer of other spaces
        than the model's is refused, and the model keeps its buffer."""
        previous = self.replay_buffer
        super().load_replay_buffer(path, truncate_last_traj)
        for name in ("observation_space", "action_space"):
            theirs, ours = getattr(self.replay_buffer, name), getattr(self, name)
            if theirs != ours:
                self.replay_buffer = previous
                raise ValueError(
                    f"The replay buffer in {path} holds transitions of the {name} {theirs}, the model's is {ours}: "
                    "load the buffer saved with this model (another environment's transitions cannot be trained on)."
                )

    def set_parameters(
        self, load_path_or_dict: ZipPath | dict[str, Any], exact_match: bool = True, device: th.device | str = "auto"
    ) -> None:
        """See :meth:`BaseAlgorithm.set_parameters`; from a file, only the tensors are read (``weights_only=True``)."""
        if not isinstance(load_path_or_dict, dict):
            load_path_or_dict = _read_tensors(_zip_path(load_path_or_dict), device)[0]
        super().set_parameters(load_path_or_dict, exact_match=exact_match, device=device)  # type: ignore[arg-type]

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "actor", "critic", "critic_target"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", "actor.optimizer", "critic.optimizer"], []


def safe_save(model: BaseAlgorithm, path: str | pathlib.Path) -> None:
    """Save any SB3 algorithm (e.g. ``SAC``) as ``model.save(path)``, atomically, for :func:`safe_load` to read."""
    if isinstance(model, TwinCriticPersistence):
        model.save(path)
    else:
        _save_with_entry(model, path, model.save)


def _save_with_entry(model: BaseAlgorithm, path: ZipPath, save: Callable[[io.BytesIO], None]) -> None:
    """The zip ``save`` writes, with :data:`SAFE_ENTRY` added, written to a stream or atomically to a file."""
    with io.BytesIO() as buffer:
        save(buffer)
        with zipfile.ZipFile(buffer, "a") as archive:
            archive.writestr(SAFE_ENTRY, json.dumps(_safe_entry(model, json.loads(archive.read("data")))))
        content = buffer.getvalue()
    if isinstance(path, io.BufferedIOBase):
        path.write(content)
        return
    with atomic_path(save_path_with_suffix(path, "zip")) as temporary:
        temporary.write_bytes(content)


def _safe_entry(model: BaseAlgorithm, data: dict[str, Any]) -> dict[str, Any]:
    """The JSON of :data:`SAFE_ENTRY`: what ``data`` pickled, as plain values, and what it could not encode."""
    aliases = [alias for alias, policy in model.policy_aliases.items() if type(model.policy) is policy]
    objects, not_encoded = {}, {}
    for key, value in data.items():
        if not (isinstance(value, dict) and ":serialized:" in value) or key in _RESTARTED or key == "policy_class":
            continue
        try:
            objects[key] = _encode(key, getattr(model, key))
        except TypeError as error:
            if key not in _RESUMED:
                not_encoded[key] = str(error)
    policy = aliases[0] if aliases else None
    return {"algorithm": type(model).__name__, "policy": policy, "objects": objects, "not_encoded": not_encoded}


def _read_tensors(path: ZipPath, device: th.device | str = "auto") -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The state dicts and PyTorch variables of a model zip, read with ``torch.load(weights_only=True)``."""
    try:
        _, params, pytorch_variables = load_from_zip_file(path, load_data=False, device=device)
    except pickle.UnpicklingError as error:
        raise UnsafeFileError(
            f"{path} holds weights with objects other than tensors, which torch.load(weights_only=True) refuses to "
            f"unpickle ({str(error).splitlines()[-1][:200]}). {_IF_TRUSTED}"
        ) from None
    return params or {}, pytorch_variables


def _zip_path(path: ZipPath) -> ZipPath:
    """A stream as it is; ``path``, or ``path.zip`` when only that exists (as SB3 looks it up)."""
    if isinstance(path, io.BufferedIOBase):
        return path
    for candidate in (pathlib.Path(path), pathlib.Path(f"{path}.zip")):
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(f"No model file at {path} (nor {path}.zip)")


def _read_json_parts(path: ZipPath) -> tuple[dict[str, Any] | None, dict[str, Any]]:
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
    """The lower-case name of the algorithm that saved a model zip, from ``sb3_dacerf.json`` or else the policy class's
    module (``sac`` for ``stable_baselines3.sac.policies``), read as JSON; ``None`` if neither names one."""
    try:
        return _algorithm_name(*_read_json_parts(_zip_path(path)))  # type: ignore[arg-type]
    except (OSError, ValueError):
        return None


def _algorithm_name(entry: dict[str, Any] | None, data: dict[str, Any]) -> str | None:
    if entry is not None and isinstance(entry.get("algorithm"), str):
        return entry["algorithm"].lower()
    policy_class = data.get("policy_class")
    module = policy_class.get("__module__") if isinstance(policy_class, dict) else None
    parts = module.split(".") if isinstance(module, str) else []
    if len(parts) >= 3 and parts[0] in ("stable_baselines3", "sb3_contrib", "sb3_dacerf") and parts[-1] == "policies":
        return parts[1]
    return None


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
        elif key not in _RESTARTED | _RESUMED:
            unsafe[key] = not_encoded.get(key, value.get(":type:", "a pickled object"))
    if unsafe:
        listing = "; ".join(f"{key} ({why})" for key, why in unsafe.items())
        raise UnsafeFileError(
            f"{path} holds objects that exist only as pickles: {listing}. Pass their values with "
            f"custom_objects={{{', '.join(repr(key) + ': ...' for key in unsafe)}}} (e.g. 'learning_rate': 0.0 to "
            f"predict only). {_IF_TRUSTED}"
        )
    for key in ("observation_space", "action_space", "policy_kwargs"):
        if key not in rebuilt:
            raise ValueError(f"{path} has no {key} in its data: it is not a complete file written by {cls.__name__}.save")
        if key.endswith("_space"):
            rebuilt[key] = _convert_space(rebuilt[key])
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
    if schedule in _SCHEDULES:
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
    if not isinstance(value, dict):
        return value
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
        if value["schedule"] not in _SCHEDULES:
            raise UnsafeFileError(f"The file names the schedule {value['schedule']!r}, none of {sorted(_SCHEDULES)}")
        module, _, name = value["schedule"].rpartition(".")
        schedule = object.__new__(getattr(importlib.import_module(module), name))
        schedule.__dict__.update({k: _decode_value(v) for k, v in value["fields"].items()})  # what unpickling does
        return schedule
    return {k: _decode_value(v) for k, v in value["dict"].items()}


def space_to_json(space: spaces.Space) -> dict[str, Any]:
    """A Box, Discrete, MultiDiscrete, MultiBinary or Dict space as JSON (:func:`space_from_json` reads it back)."""
    if isinstance(space, spaces.Box):
        low, high = (np.asarray(bound, dtype=np.float64).tolist() for bound in (space.low, space.high))
        return {"Box": {"low": low, "high": high, "shape": list(space.shape), "dtype": str(space.dtype)}}
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
            low, high = (np.asarray(fields[bound], dtype=np.float64).astype(fields["dtype"]) for bound in ("low", "high"))
            return spaces.Box(low, high, tuple(fields["shape"]), fields["dtype"])
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


def _rms_to_json(rms: RunningMeanStd | dict[str, RunningMeanStd]) -> dict[str, Any]:
    if isinstance(rms, dict):
        return {"dict": {key: _rms_to_json(value) for key, value in rms.items()}}
    encoded: dict[str, Any] = {"mean": rms.mean.tolist(), "var": rms.var.tolist(), "count": float(rms.count)}
    if isinstance(rms, MaskedRowsRunningMeanStd):
        encoded.update(rows=list(rms.rows), row_rms=_rms_to_json(rms.row_rms))
    return encoded


def _rms_from_json(encoded: dict[str, Any]) -> Any:
    if "dict" in encoded:
        return {key: _rms_from_json(value) for key, value in encoded["dict"].items()}
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


def _settings(value_of: Callable[[str], Any]) -> dict[str, Any]:
    """A VecNormalize's settings, each read with ``value_of(name)``."""
    settings: dict[str, Any] = {key: bool(value_of(key)) for key in ("norm_obs", "norm_reward", "training")}
    settings.update({key: float(value_of(key)) for key in ("clip_obs", "clip_reward", "gamma", "epsilon")})
    return {**settings, "norm_obs_keys": value_of("norm_obs_keys")}


def save_vec_normalize(vec_normalize: VecNormalize, path: str | os.PathLike) -> None:
    """Write a ``VecNormalize``'s statistics and settings as JSON, atomically; :func:`load_vec_normalize` reads them."""
    masked = isinstance(vec_normalize, MaskedVecNormalize)
    encoded = {
        "class": "MaskedVecNormalize" if masked else "VecNormalize",
        "observation_space": space_to_json(vec_normalize.observation_space),
        "action_space": space_to_json(vec_normalize.action_space),
        **_settings(lambda key: getattr(vec_normalize, key)),
        "rows": list(vec_normalize.rows) if masked else None,  # type: ignore[attr-defined]
        "obs_rms": _rms_to_json(vec_normalize.obs_rms),
        "ret_rms": _rms_to_json(vec_normalize.ret_rms),
    }
    with atomic_path(path) as temporary:
        temporary.write_text(json.dumps(encoded))


def load_vec_normalize(path: str | os.PathLike, venv: VecEnv | None = None) -> VecNormalize:
    """
    The ``VecNormalize`` (or ``MaskedVecNormalize``) written by :func:`save_vec_normalize`, wrapping ``venv`` if given;
    without it, it normalises observations (``normalize_obs``) and can be exported, but not stepped. Reads JSON only.

    :raises ValueError: a file that is not such JSON, or ``venv``'s spaces differ from the statistics'
    """
    try:
        encoded = json.loads(pathlib.Path(path).read_text())
        classes: dict[str, type[VecNormalize]] = {"VecNormalize": VecNormalize, "MaskedVecNormalize": MaskedVecNormalize}
        cls = classes[encoded["class"]]
        state = {
            "observation_space": space_from_json(encoded["observation_space"]),
            "action_space": space_from_json(encoded["action_space"]),
            **_settings(encoded.__getitem__),
            "obs_rms": _rms_from_json(encoded["obs_rms"]),
            "ret_rms": _rms_from_json(encoded["ret_rms"]),
        }
        # What a VecNormalize without environment still has (set_venv replaces them)
        state.update(num_envs=1, render_mode=None, metadata={}, reset_infos=[{}], _seeds=[None], _options=[{}])
        state.update(old_obs=np.array([]), old_reward=np.array([]), returns=np.zeros(1))
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
        normalizer.reset_infos = [{} for _ in range(venv.num_envs)]
        normalizer._seeds, normalizer._options = [None] * venv.num_envs, [{}] * venv.num_envs
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
    lines = path.read_text().splitlines() if path.is_file() else []
    sums = (line.strip().partition("  ") for line in lines)
    return {name.lstrip("*"): digest.lower() for digest, _, name in sums if name}


def check_sha256(path: str | os.PathLike) -> None:
    """
    Check a file against the ``SHA256SUMS`` of its folder if that lists it (the shipped drivers of ``examples/models/``).

    :raises ValueError: the file's digest differs from the listed one, naming both
    """
    path = pathlib.Path(path)
    expected = read_sha256sums(path.parent).get(path.name)
    if expected is not None and (actual := sha256(path)) != expected:
        raise ValueError(
            f"{path} does not match its checksum in {path.parent / CHECKSUMS} (sha256 {actual}, listed {expected}): "
            "the file was changed or corrupted; download it again (or, for a file you changed yourself, update "
            f"{CHECKSUMS} with `sha256sum`)."
        )


def update_sha256sums(paths: list[str | os.PathLike]) -> None:
    """Write the digests of ``paths`` into the ``SHA256SUMS`` of their folders (other entries are kept)."""
    files = [pathlib.Path(path) for path in paths]
    for folder in {file.parent for file in files}:
        sums = {**read_sha256sums(folder), **{file.name: sha256(file) for file in files if file.parent == folder}}
        with atomic_path(folder / CHECKSUMS) as temporary:
            temporary.write_text("".join(f"{digest}  {name}\n" for name, digest in sorted(sums.items())))
