"""
The data regime of an off-policy run, ``S`` environment steps per gradient step: ``sample_batch_size / sample_interval``
in GOPS (the DACER-F paper's trainer), ``train_freq * n_envs / gradient_steps`` in SB3 (see the "Data regime" page).
"""

from fractions import Fraction
from math import ceil
from typing import Any


def steps_per_gradient_kwargs(steps_per_gradient: str | float | Fraction, n_envs: int = 1) -> dict[str, int]:
    """
    SB3's ``train_freq`` and ``gradient_steps`` for ``S`` environment steps per gradient step with ``n_envs``
    environments: for a whole ``S`` (a multiple of ``n_envs``) ``train_freq=S // n_envs, gradient_steps=1``, as GOPS's
    sampler; for ``S = 1/G`` (``"1/4"``, ``0.25``) ``train_freq=1, gradient_steps=G * n_envs``.

    :raises ValueError: if ``S`` and ``n_envs`` do not fit, with the values that would
    """
    try:
        steps = Fraction(str(steps_per_gradient))
    except (ValueError, ZeroDivisionError):
        raise ValueError(f"steps per gradient step {steps_per_gradient!r} is not a number: pass e.g. 200, 1 or 1/4") from None
    if steps <= 0:
        raise ValueError(f"steps per gradient step must be positive, got {steps_per_gradient}: pass e.g. 200, 1 or 1/4")
    if n_envs < 1:
        raise ValueError(f"n_envs must be at least 1, got {n_envs}")
    if steps >= 1:
        if steps.denominator != 1:
            raise ValueError(
                f"{steps_per_gradient} environment steps per gradient step: above 1 it must be a whole number "
                f"(e.g. {ceil(steps)})"
            )
        if steps.numerator % n_envs:
            divisors = [n for n in range(1, min(steps.numerator, 16) + 1) if steps.numerator % n == 0]
            raise ValueError(
                f"{steps.numerator} environment steps per gradient step is not a multiple of n_envs {n_envs}: every "
                f"rollout steps all the environments, so use n_envs in {divisors} (divisors of {steps.numerator}) or a "
                f"multiple of {n_envs} steps per gradient step"
            )
        return dict(train_freq=steps.numerator // n_envs, gradient_steps=1)
    if steps.numerator != 1:
        raise ValueError(
            f"{steps_per_gradient} environment steps per gradient step: below 1 it must be 1/G for a whole number G "
            "of gradient steps per environment step (e.g. 1/2, 0.25)"
        )
    return dict(train_freq=1, gradient_steps=steps.denominator * n_envs)


def transitions_per_rollout(steps_per_gradient: str | float | Fraction | None, n_envs: int = 1) -> int:
    """Transitions between two rounds of gradient steps (``train_freq * n_envs``); ``S=None``: SB3's default of one step."""
    if steps_per_gradient is None:
        return n_envs
    return steps_per_gradient_kwargs(steps_per_gradient, n_envs)["train_freq"] * n_envs


def gops_off_serial_to_sb3(
    sample_batch_size: int,
    replay_batch_size: int,
    max_iteration: int,
    buffer_warm_size: int = 0,
    sample_interval: int = 1,
    n_envs: int = 1,
) -> dict[str, Any]:
    """
    The SB3 settings of a run of GOPS's off-policy serial trainer, named as GOPS names them (``n_envs``: its
    ``vector_env_num``): the same transitions, gradient steps and replay batches, in the same order (GOPS's warm-up
    samples the initial policy, SB3's random actions).

    :return: ``n_envs``, ``train_freq``, ``gradient_steps``, ``batch_size`` and ``learning_starts`` (the algorithm's
        settings), ``total_timesteps`` (for ``learn``), ``total_gradient_steps`` and ``steps_per_gradient`` (``S``)
    """
    counts = dict(sample_batch_size=sample_batch_size, replay_batch_size=replay_batch_size, max_iteration=max_iteration)
    counts.update(sample_interval=sample_interval, n_envs=n_envs)
    for name, value in counts.items():
        if value < 1:
            raise ValueError(f"{name} must be at least 1, got {value}")
    if buffer_warm_size < 0:
        raise ValueError(f"buffer_warm_size must be at least 0, got {buffer_warm_size}")
    if sample_batch_size % n_envs:
        raise ValueError(
            f"sample_batch_size {sample_batch_size} is not a multiple of n_envs {n_envs} (GOPS's sampler refuses it "
            "too): choose n_envs among its divisors"
        )
    warm = ceil(buffer_warm_size / sample_batch_size) * sample_batch_size
    samplings = ceil(max_iteration / sample_interval)
    return dict(
        n_envs=n_envs,
        train_freq=sample_batch_size // n_envs,
        gradient_steps=sample_interval,
        batch_size=replay_batch_size,
        learning_starts=warm,
        total_timesteps=warm + samplings * sample_batch_size,
        total_gradient_steps=samplings * sample_interval,  # GOPS may stop its last sampling's iterations earlier
        steps_per_gradient=Fraction(sample_batch_size, sample_interval),
    )
