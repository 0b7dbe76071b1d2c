"""
Saving and loading of :class:`~sb3_dacerf.common.twin_critic.TwinCriticAlgorithm`: atomic writes of models and
replay buffers, a clear refusal of another algorithm's file, and parameters saved with separate critic networks
converted to the ensemble critics.
"""

import base64
import io
import json
import os
import pathlib
import zipfile
from typing import Any

import cloudpickle
import torch as th
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.save_util import load_from_zip_file

from sb3_dacerf.common.policies import EnsembleCritic, convert_separate_critics_optimizer
from sb3_dacerf.common.utils import atomic_path, save_path_with_suffix


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
        See :meth:`BaseAlgorithm.save`; a file path is written atomically: to a temporary file in the same folder,
        renamed over ``path`` once complete, so a failed save (full disk, interruption) leaves the previous file intact.
        """
        if isinstance(path, io.BufferedIOBase):
            super().save(path, exclude, include)
            return
        with atomic_path(save_path_with_suffix(path, "zip")) as temporary:
            super().save(temporary, exclude, include)

    def save_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase) -> None:
        """
        See :meth:`OffPolicyAlgorithm.save_replay_buffer`; a file path is written atomically, like :meth:`save`.
        """
        if isinstance(path, io.BufferedIOBase):
            super().save_replay_buffer(path)
            return
        with atomic_path(save_path_with_suffix(path, "pkl")) as temporary:
            super().save_replay_buffer(temporary)

    @classmethod
    def load(cls, path: str | pathlib.Path | io.BufferedIOBase, *args: Any, **kwargs: Any) -> Any:
        """
        See :meth:`BaseAlgorithm.load`; a file saved by another algorithm (e.g. SAC) is refused with its name.
        """
        policy_class = saved_policy_class(path)
        expected = cls.policy_aliases["MlpPolicy"]
        if isinstance(policy_class, type) and not issubclass(policy_class, expected):
            algorithm = _algorithm_of(policy_class)
            raise ValueError(
                f"{path} holds a {algorithm} model (policy {policy_class.__module__}.{policy_class.__qualname__}), "
                f"not a {cls.__name__} model: load it with {algorithm}.load(...)."
            )
        return super().load(path, *args, **kwargs)

    def _excluded_save_params(self) -> list[str]:
        return super()._excluded_save_params() + ["actor", "critic", "critic_target"]  # noqa: RUF005

    def set_parameters(
        self,
        load_path_or_dict: str | pathlib.Path | io.BufferedIOBase | dict[str, Any],
        exact_match: bool = True,
        device: th.device | str = "auto",
    ) -> None:
        """
        See :meth:`BaseAlgorithm.set_parameters`. Parameters saved by versions with separate critic networks load too:
        the networks' entries are stacked into the ensemble critics' (``EnsembleCritic``), and so is the state of
        the critic optimizer.
        """
        if isinstance(load_path_or_dict, dict):
            params = load_path_or_dict
        else:
            _, params, _ = load_from_zip_file(load_path_or_dict, device=device)
        optimizer_state = params.get("critic.optimizer") if isinstance(params, dict) else None
        # Only ensemble critics have a separate-network layout to convert from (DSAC's Gaussian critics do not)
        if (
            isinstance(self.critic, EnsembleCritic)
            and isinstance(optimizer_state, dict)
            and len(optimizer_state.get("param_groups", [])) == 1
        ):
            saved_count = len(optimizer_state["param_groups"][0]["params"])
            current = self.critic.optimizer.param_groups[0]["params"]
            n_ensemble = sum(1 for _ in self.critic.ensemble.parameters())
            if saved_count != len(current) and self.critic.n_critics > 1:
                params = {
                    **params,
                    "critic.optimizer": convert_separate_critics_optimizer(
                        optimizer_state, self.critic, n_leading=len(current) - n_ensemble
                    ),
                }
        super().set_parameters(params, exact_match=exact_match, device=device)

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        return state_dicts, []


def saved_policy_class(path: Any) -> type | None:
    """The policy class recorded in a model zip, or ``None`` when it cannot be read (SB3's load then reports why)."""
    if not isinstance(path, (str, os.PathLike)):
        return None
    path = pathlib.Path(path)
    if not path.is_file() and pathlib.Path(f"{path}.zip").is_file():
        path = pathlib.Path(f"{path}.zip")
    try:
        with zipfile.ZipFile(path) as archive:
            serialized = json.loads(archive.read("data"))["policy_class"][":serialized:"]
        return cloudpickle.loads(base64.b64decode(serialized.encode()))
    except Exception:
        return None


def algorithm_name(policy_class: type | None) -> str | None:
    """
    The lower-case name of the algorithm a policy class belongs to: ``sac`` for
    ``stable_baselines3.sac.policies.SACPolicy``, ``tqc`` for sb3_contrib's, ``dacer`` for ours; ``None`` for a policy
    of another package (or ``None``, a class :func:`saved_policy_class` could not read).
    """
    parts = policy_class.__module__.split(".") if isinstance(policy_class, type) else []
    if len(parts) >= 3 and parts[0] in ("stable_baselines3", "sb3_contrib", "sb3_dacerf") and parts[-1] == "policies":
        return parts[1]
    return None


def _algorithm_of(policy_class: type) -> str:
    """``SAC`` for ``stable_baselines3.sac.policies.SACPolicy``, ``TQC`` for sb3_contrib's, ``DACER`` for ours."""
    name = algorithm_name(policy_class)
    return name.upper() if name else f"another algorithm's (whose policy is {policy_class.__name__})"
