"""
Normalisation of observations that hold a table of optional rows, such as the driving scenarios' vehicle slots: SB3's
``VecNormalize`` clips an empty slot that training always saw filled to ``±clip_obs``, :class:`MaskedVecNormalize`
gives it zeros.
"""

from __future__ import annotations

import copy
import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import VecEnv, VecNormalize


def _table(array: np.ndarray, rows: tuple[int, int, int]) -> np.ndarray:
    """The table of ``array``'s last axis, shape ``(..., count, size)``."""
    start, count, size = rows
    return array[..., start : start + count * size].reshape(*array.shape[:-1], count, size)


class MaskedRowsRunningMeanStd(RunningMeanStd):
    """SB3's running mean and variance of flat observations whose table of ``rows`` (see :class:`MaskedVecNormalize`)
    has the statistics of the present rows (mask > 0.5) pooled over the rows, feature by feature (``row_rms``)."""

    def __init__(self, shape: tuple[int, ...], rows: tuple[int, int, int], epsilon: float = 1e-4):
        super().__init__(epsilon=epsilon, shape=shape)
        self.rows = rows
        self.row_rms = RunningMeanStd(epsilon=epsilon, shape=(rows[2],))
        self._spread_row_statistics()

    def _spread_row_statistics(self) -> None:
        start, count, size = self.rows
        self.mean[start : start + count * size] = np.tile(self.row_rms.mean, count)
        self.var[start : start + count * size] = np.tile(self.row_rms.var, count)

    def update(self, arr: np.ndarray) -> None:
        """:param arr: a batch of observations, shape ``(batch, n)``"""
        super().update(arr)  # every entry; the table's entries are then replaced by the present rows' statistics
        table = _table(arr, self.rows).reshape(-1, self.rows[2])
        present = table[table[:, -1] > 0.5]
        if len(present):
            self.row_rms.update(present)
        self._spread_row_statistics()

    def copy(self) -> MaskedRowsRunningMeanStd:
        return copy.deepcopy(self)

    def combine(self, other: RunningMeanStd) -> None:
        """:raises ValueError: statistics of another kind or layout than ``MaskedRowsRunningMeanStd`` of the same ``rows``"""
        if not isinstance(other, MaskedRowsRunningMeanStd) or other.rows != self.rows:
            raise ValueError(
                f"Cannot combine the statistics of rows {self.rows} with {type(other).__name__}"
                f"{' of rows ' + str(other.rows) if isinstance(other, MaskedRowsRunningMeanStd) else ''}: combine "
                "statistics of the same MaskedVecNormalize layout"
            )
        super().combine(other)
        self.row_rms.combine(other.row_rms)
        self._spread_row_statistics()


class MaskedVecNormalize(VecNormalize):
    """
    SB3's ``VecNormalize`` for flat ``Box`` observations that hold a table of ``count`` optional rows of ``size``
    entries from index ``start``, each row's last entry its mask (1: present, 0: empty). A present row's entries are
    normalised with the statistics of that feature over the present rows of every slot, its mask stays 1; an empty row
    becomes zeros; the other entries are normalised as ``VecNormalize`` does. It saves and loads as ``VecNormalize``
    (``VecNormalize.load`` gives back this class); evaluation envs that copy its statistics must be of this class too.

    :param venv: the vectorized environment
    :param rows: ``(start, count, size)``; for the driving scenarios
        :func:`sb3_dacerf.envs.driving.common.observation.vehicle_rows` gives it
    :param kwargs: ``VecNormalize``'s arguments (``training``, ``norm_obs``, ``norm_reward``, ``clip_obs``, ...)
    """

    def __init__(self, venv: VecEnv, rows: Sequence[int], **kwargs: Any):
        space = venv.observation_space
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise ValueError(f"MaskedVecNormalize needs a flat Box observation space, got {space}: use VecNormalize")
        if len(rows) != 3 or not all(isinstance(v, numbers.Integral) and not isinstance(v, bool) for v in rows):
            raise ValueError(f"rows must be (start, count, size), three integers, got {rows!r}")
        start, count, size = (int(v) for v in rows)
        if start < 0 or count < 0 or size < 2 or start + count * size > space.shape[0]:
            raise ValueError(
                f"rows (start={start}, count={count}, size={size}) do not fit observations of {space.shape[0]} entries: "
                "a table of count rows of size >= 2 entries (the last one the mask) from index start must end at "
                f"or before {space.shape[0]}"
            )
        super().__init__(venv, **kwargs)
        self.rows = (start, count, size)
        if self.norm_obs:
            self.obs_rms = MaskedRowsRunningMeanStd(space.shape, self.rows)  # type: ignore[assignment]  # (VecNormalize types it for Dict spaces too)

    def _mask_rows(self, obs: np.ndarray, transformed: np.ndarray) -> np.ndarray:
        """``transformed`` with each row of ``obs``'s table zeroed where it is empty and its mask entry set to 0 / 1."""
        start, count, size = self.rows
        present = _table(np.asarray(obs), self.rows)[..., -1:] > 0.5
        table = np.where(present, _table(transformed, self.rows), 0.0)
        table[..., -1] = present[..., 0]
        transformed = np.array(transformed, copy=True)
        transformed[..., start : start + count * size] = table.reshape(*transformed.shape[:-1], count * size)
        return transformed

    def _normalize_obs(self, obs: np.ndarray, obs_rms: RunningMeanStd) -> np.ndarray:
        return self._mask_rows(obs, super()._normalize_obs(obs, obs_rms))

    def _unnormalize_obs(self, obs: np.ndarray, obs_rms: RunningMeanStd) -> np.ndarray:
        return self._mask_rows(obs, super()._unnormalize_obs(obs, obs_rms))
