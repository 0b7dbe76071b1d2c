"""
Arguments that were removed or renamed, from a user, an RL Zoo YAML file or the saved data of an older model: each
either converts to its replacement with a ``FutureWarning`` that names it, or raises a ``ValueError`` that says what to
use instead. Nothing is silently dropped when it would change what the model does.
"""

import warnings
from typing import Any


def warn_renamed(old: str, new: str, stacklevel: int = 3) -> None:
    """
    A ``FutureWarning``: ``old`` is deprecated, ``new`` replaces it (it is converted this time).

    :param old: What was given, as the user wrote it (e.g. ``"policy_kwargs critic_layer_norm=True"``)
    :param new: What to write instead
    :param stacklevel: As for :func:`warnings.warn`, so that the warning points at the user's call
    """
    warnings.warn(
        f"{old} is deprecated and will be removed: use {new} instead (converted this time).", FutureWarning, stacklevel=stacklevel
    )


def critic_from_flags(policy_kwargs: dict[str, Any], owner: str) -> dict[str, Any]:
    """
    A copy of ``policy_kwargs`` in which the deprecated booleans ``critic_layer_norm`` / ``critic_batch_renorm``
    (older versions, older saved models and RL Zoo files) are replaced by the ``critic`` choice they meant, with a
    ``FutureWarning``; unchanged when it holds neither.

    :param policy_kwargs: The ``policy_kwargs`` of an algorithm
    :param owner: Who they belong to, for the messages (e.g. ``"DACERF"``)
    :return: ``policy_kwargs`` with ``critic`` instead of the booleans
    :raises ValueError: when the booleans contradict each other or a ``critic`` given with them
    """
    flags = {name: policy_kwargs[name] for name in ("critic_layer_norm", "critic_batch_renorm") if name in policy_kwargs}
    if not flags:
        return policy_kwargs
    layer_norm, batch_renorm = bool(flags.get("critic_layer_norm", False)), bool(flags.get("critic_batch_renorm", False))
    given = ", ".join(f"{name}={value!r}" for name, value in flags.items())
    if layer_norm and batch_renorm:
        raise ValueError(
            f"{owner}: policy_kwargs {given} ask for two kinds of critics at once. These booleans are replaced by one "
            "choice: policy_kwargs=dict(critic='layer_norm') or dict(critic='batch_renorm') (or 'mlp')."
        )
    critic = "layer_norm" if layer_norm else "batch_renorm" if batch_renorm else "mlp"
    if "critic" in policy_kwargs and policy_kwargs["critic"] != critic:
        raise ValueError(
            f"{owner}: policy_kwargs critic={policy_kwargs['critic']!r} and the deprecated {given} (critic={critic!r}) "
            "disagree: give critic alone."
        )
    warn_renamed(f"policy_kwargs {given}", f"policy_kwargs=dict(critic={critic!r})", stacklevel=4)
    converted = {key: value for key, value in policy_kwargs.items() if key not in flags}
    converted["critic"] = critic
    return converted


def policy_kwarg_from_argument(
    policy_kwargs: dict[str, Any], name: str, value: Any, owner: str, stacklevel: int = 4
) -> dict[str, Any]:
    """
    ``name`` given to the algorithm's constructor, where it is deprecated (it is a policy argument): a
    ``FutureWarning``, and a copy of ``policy_kwargs`` holding it.

    :param policy_kwargs: The algorithm's ``policy_kwargs`` (not modified)
    :param name: The argument's name (e.g. ``"n_sampling_steps"``)
    :param value: Its value, as given to the constructor
    :param owner: The algorithm, for the messages (e.g. ``"DACERF"``)
    :param stacklevel: As for :func:`warnings.warn`, counted from :func:`warn_renamed`
    :return: ``policy_kwargs`` holding ``name=value``
    :raises ValueError: when ``policy_kwargs`` holds another value of ``name`` (neither silently wins)
    """
    if name in policy_kwargs and policy_kwargs[name] != value:
        raise ValueError(
            f"{owner}: {name}={value!r} and policy_kwargs=dict({name}={policy_kwargs[name]!r}) disagree: "
            f"give it once, as policy_kwargs=dict({name}=...)."
        )
    warn_renamed(f"{owner}({name}=...)", f"policy_kwargs=dict({name}={value!r})", stacklevel=stacklevel)
    return {**policy_kwargs, name: value}


def reject_unknown_arguments(owner: str, arguments: dict[str, Any]) -> None:
    """
    Python's own ``TypeError`` for keyword arguments that no conversion took.

    :param owner: The class whose constructor was called (e.g. ``"DACERF"``)
    :param arguments: The keyword arguments left over (nothing happens when empty)
    :raises TypeError: naming the first of them
    """
    if arguments:
        raise TypeError(f"{owner}.__init__() got an unexpected keyword argument {next(iter(arguments))!r}")
