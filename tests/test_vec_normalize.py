"""Tests of MaskedVecNormalize: observation normalisation of a table of optional rows (the driving vehicle slots)."""

import numpy as np
import pytest
from conftest import TABLE_ROWS, TableEnv
from gymnasium import spaces
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize, sync_envs_normalization

from sb3_dacerf.common.vec_normalize import MaskedRowsRunningMeanStd, MaskedVecNormalize


def collect(venv, steps: int) -> np.ndarray:
    venv.seed(0)
    venv.reset()
    raw = [venv.get_original_obs()]
    for _ in range(steps):
        venv.step(np.zeros((venv.num_envs, *venv.action_space.shape), dtype=np.float32))
        raw.append(venv.get_original_obs())
    return np.concatenate(raw)


def test_rows_get_the_pooled_statistics_of_present_rows_and_empty_rows_zeros():
    venv = MaskedVecNormalize(DummyVecEnv([TableEnv, TableEnv]), rows=TABLE_ROWS, norm_reward=False)
    raw = collect(venv, 200)
    table = raw[:, 2:].reshape(-1, 3)
    present = table[table[:, 2] == 1]
    assert 0 < len(present) < len(table)  # both kinds of rows were seen
    np.testing.assert_allclose(venv.obs_rms.row_rms.mean[:2], present[:, :2].mean(axis=0), rtol=1e-4)
    np.testing.assert_allclose(venv.obs_rms.row_rms.var[:2], present[:, :2].var(axis=0), rtol=1e-3)
    np.testing.assert_allclose(venv.obs_rms.mean[:2], raw[:, :2].mean(axis=0), rtol=1e-4)  # the others: VecNormalize's

    obs = np.array([4.0, -1.0, 50.0, 2.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=np.float32)
    normalized = venv.normalize_obs(obs)
    std = np.sqrt(venv.obs_rms.row_rms.var[:2] + venv.epsilon)
    np.testing.assert_allclose(normalized[2:4], (obs[2:4] - venv.obs_rms.row_rms.mean[:2]) / std, rtol=1e-5)
    assert normalized[4] == 1.0  # the mask as it is
    np.testing.assert_array_equal(normalized[5:], 0.0)  # empty rows: zeros, mask 0
    plain = VecNormalize(DummyVecEnv([TableEnv]), norm_reward=False)
    plain.obs_rms = venv.obs_rms.copy()
    np.testing.assert_allclose(normalized[:2], plain.normalize_obs(obs)[:2])
    # and back
    np.testing.assert_allclose(venv.unnormalize_obs(normalized), obs, rtol=1e-5, atol=1e-5)


def test_empty_rows_stay_in_range_where_vecnormalize_clips_them():
    # Trained where every row is present, then shown one present row: VecNormalize clips the empty rows' masks at
    # -clip_obs (their variance was 0), MaskedVecNormalize gives them zeros.
    full = [lambda: TableEnv(min_rows=3)]
    plain = VecNormalize(DummyVecEnv(full), norm_reward=False)
    masked = MaskedVecNormalize(DummyVecEnv(full), rows=TABLE_ROWS, norm_reward=False)
    for venv in (plain, masked):
        collect(venv, 100)
    sparse = np.array([4.0, -1.0, 50.0, 2.0, 1.0, 0, 0, 0, 0, 0, 0], dtype=np.float32)
    assert np.abs(plain.normalize_obs(sparse)).max() == pytest.approx(plain.clip_obs)
    assert np.abs(masked.normalize_obs(sparse)).max() < 3.0


def test_saves_loads_copies_and_syncs_as_vecnormalize_does(tmp_path):
    venv = MaskedVecNormalize(DummyVecEnv([TableEnv]), rows=TABLE_ROWS, norm_reward=False)
    collect(venv, 50)
    obs = collect(MaskedVecNormalize(DummyVecEnv([TableEnv]), rows=TABLE_ROWS), 5)
    venv.save(tmp_path / "stats.pkl")
    loaded = VecNormalize.load(tmp_path / "stats.pkl", DummyVecEnv([TableEnv]))
    assert isinstance(loaded, MaskedVecNormalize) and isinstance(loaded.obs_rms, MaskedRowsRunningMeanStd)
    loaded.training = False
    np.testing.assert_array_equal(loaded.normalize_obs(obs), venv.normalize_obs(obs))
    evaluation = MaskedVecNormalize(DummyVecEnv([TableEnv]), rows=TABLE_ROWS, training=False)
    sync_envs_normalization(venv, evaluation)
    np.testing.assert_array_equal(evaluation.normalize_obs(obs), venv.normalize_obs(obs))
    copy = venv.obs_rms.copy()
    copy.combine(venv.obs_rms)  # the same data twice: the same statistics
    np.testing.assert_allclose(copy.row_rms.mean, venv.obs_rms.row_rms.mean)
    np.testing.assert_allclose(copy.mean, venv.obs_rms.mean)
    with pytest.raises(ValueError, match=r"Cannot combine the statistics of rows \(2, 3, 3\) with RunningMeanStd"):
        copy.combine(VecNormalize(DummyVecEnv([TableEnv])).obs_rms)


@pytest.mark.parametrize(
    "rows, message",
    [
        ((2, 3), r"rows must be \(start, count, size\), three integers, got \(2, 3\)"),
        ((2, 3, 1.5), r"three integers"),
        ((2, 4, 3), r"rows \(start=2, count=4, size=3\) do not fit observations of 11 entries"),
        ((2, 3, 1), r"size >= 2"),
        ((-1, 3, 3), r"do not fit"),
    ],
)
def test_bad_rows_raise_clear_errors(rows, message):
    with pytest.raises(ValueError, match=message):
        MaskedVecNormalize(DummyVecEnv([TableEnv]), rows=rows)


class DictTableEnv(TableEnv):
    observation_space = spaces.Dict({"table": spaces.Box(-np.inf, np.inf, shape=(11,), dtype=np.float32)})


def test_refuses_observations_that_are_not_flat_boxes():
    with pytest.raises(ValueError, match=r"needs a flat Box observation space.*use VecNormalize"):
        MaskedVecNormalize(DummyVecEnv([DictTableEnv]), rows=TABLE_ROWS)
