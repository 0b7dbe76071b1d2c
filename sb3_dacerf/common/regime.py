"""
The data regime of an off-policy run: how many environment steps it collects per gradient step.

GOPS, the trainer of the DACER-F paper, counts *iterations*: its off-policy serial trainer collects
``sample_batch_size`` transitions every ``sample_interval`` iterations and makes one gradient step on
``replay_batch_size`` transitions per iteration, after filling the buffer with ``buffer_warm_size`` transitions.
Stable-Baselines3 counts environment steps: every ``train_freq`` steps of its ``n_envs`` environments
(``train_freq * n_envs`` transitions) it makes ``gradient_steps`` gradient steps on ``batch_size`` transitions, after
``learning_starts`` transitions. Both describe the same thing with ``S``, the environment steps per gradient step:

- GOPS: ``S = sample_batch_size / sample_interval``
- SB3: ``S = train_freq * n_envs / gradient_steps``

:func:`steps_per_gradient_kwargs` gives SB3's ``train_freq`` and ``gradient_steps`` for a chosen ``S``;
:func:`gops_off_serial_to_sb3` translates a whole GOPS configuration. The documentation page "Data regime" works the
paper's table out.
"""

from fractions import Fraction
from math import ceil
from typing import Any


def parse_steps_per_gradient(value: str | float | Fraction) -> Fraction:
    """
    Read a number of environment steps per gradient step: a whole number (``"200"``), or below 1 the inverse of a
    whole number written as a fraction or a decimal (``"1/4"``, ``"0.25"``: four gradient steps per environment step).

    :param value: the number, as given on a command line or in code
    :return: the number as an exact fraction
    :raises ValueError: if it is not a positive number
    """
    try:
        steps = Fraction(str(value))
    except (ValueError, ZeroDivisionError):
        raise ValueError(f"steps per gradient step {value!r} is not a number: pass e.g. 200, 1 or 1/4") from None
    if steps <= 0:
        raise ValueError(f"steps per gradient step must be positive, got {value}: pass e.g. 200, 1 or 1/4")
    return steps


def steps_per_gradient_kwargs(steps_per_gradient: str | float | Fraction, n_envs: int = 1) -> dict[str, int]:
    """
    SB3's ``train_freq`` (in steps of the vectorised environment) and ``gradient_steps`` that make ``S``
    environment steps (transitions) per gradient step with ``n_envs`` environments stepped together.

    - ``S >= 1`` (several transitions per gradient step, GOPS's regime): ``S`` must be a whole multiple of
      ``n_envs``; each rollout steps the ``n_envs`` environments ``S / n_envs`` times, then makes one gradient step
      (``train_freq=S // n_envs``, ``gradient_steps=1``), as GOPS's sampler steps its vector environment
      ``sample_batch_size / num_envs`` times.
    - ``S < 1`` (several gradient steps per transition): ``1 / S`` must be a whole number ``G``; each rollout steps
      the environments once and makes ``G * n_envs`` gradient steps (``train_freq=1``).

    :param steps_per_gradient: ``S``, environment steps per gradient step (see :func:`parse_steps_per_gradient`)
    :param n_envs: environments stepped together (SB3's ``n_envs``)
    :return: ``dict(train_freq=..., gradient_steps=...)`` for the algorithm's constructor
    :raises ValueError: if ``S`` and ``n_envs`` do not fit, with the values that would
    """
    steps = parse_steps_per_gradient(steps_per_gradient)
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
    """
    Transitions collected between two rounds of gradient steps, the step in which a run's counters advance at the
    points where checkpoints can be taken: ``train_freq * n_envs``.

    :param steps_per_gradient: ``S``, or ``None`` for SB3's default of one step of the ``n_envs`` environments
    :param n_envs: environments stepped together
    :return: the number of transitions
    """
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
    The SB3 settings of a run of GOPS's off-policy serial trainer (``gops/trainer/off_serial_trainer.py``): the same
    transitions, gradient steps and replay batches, in the same order.

    GOPS first samples until its buffer holds ``buffer_warm_size`` transitions (whole sample batches, so rounded up
    to a multiple of ``sample_batch_size``), then runs ``max_iteration`` iterations; iteration ``i`` samples
    ``sample_batch_size`` transitions if ``i % sample_interval == 0`` and then makes one gradient step. SB3 makes
    its first gradient steps after the first rollout that ends beyond ``learning_starts`` transitions, so with
    ``learning_starts`` the warm-up and ``train_freq * n_envs = sample_batch_size`` the gradient steps come at the
    same transitions. One difference remains: GOPS's warm-up samples the initial policy, SB3's uniform random
    actions.

    :param sample_batch_size: GOPS's ``sample_batch_size``, transitions per sampling (over all its vector envs)
    :param replay_batch_size: GOPS's ``replay_batch_size``, transitions per gradient step
    :param max_iteration: GOPS's ``max_iteration``, the number of gradient steps
    :param buffer_warm_size: GOPS's ``buffer_warm_size``, transitions collected before the first gradient step
    :param sample_interval: GOPS's ``sample_interval``, iterations per sampling
    :param n_envs: environments stepped together (GOPS's ``vector_env_num``, SB3's ``n_envs``); must divide
        ``sample_batch_size``, as GOPS's sampler requires
    :return: ``n_envs``, ``train_freq``, ``gradient_steps``, ``batch_size`` and ``learning_starts`` (the algorithm's
        settings), ``total_timesteps`` (for ``learn``), ``total_gradient_steps`` and ``steps_per_gradient`` (``S``)
    :raises ValueError: if a count is not positive or ``n_envs`` does not divide ``sample_batch_size``
    """
    counts = dict(
        sample_batch_size=sample_batch_size,
        replay_batch_size=replay_batch_size,
        max_iteration=max_iteration,
        sample_interval=sample_interval,
        n_envs=n_envs,
    )
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
        # the last sampling may be followed by fewer than sample_interval iterations in GOPS; SB3 makes them all
        total_gradient_steps=samplings * sample_interval,
        steps_per_gradient=Fraction(sample_batch_size, sample_interval),
    )
