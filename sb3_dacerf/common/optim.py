"""Optimizer look-up by name, so RL Zoo YAML files and ``policy_kwargs`` can say ``optimizer_class="RAD"``."""

import torch as th


def get_optimizer_class(optimizer_class: type[th.optim.Optimizer] | str) -> type[th.optim.Optimizer]:
    """
    An optimizer class, given as itself or by its case-insensitive name: ``"Adam"``, ``"AdamW"``, ``"SGD"``,
    ``"RMSprop"`` (``torch.optim``) or ``"RAD"``, the DACER-F paper's relativistic adaptive gradient descent from its
    authors' optional ``pytorch-rad`` package.
    """
    if not isinstance(optimizer_class, str):
        return optimizer_class
    name = optimizer_class.lower()
    if name == "rad":
        try:
            from rad.optim import RAD
        except ImportError as error:
            hint = "pip install pytorch-rad  (or: pip install 'sb3_dacerf[rad]')"
            raise ImportError(f"The RAD optimizer needs the pytorch-rad package: {hint}") from error
        return RAD
    for torch_name in ("Adam", "AdamW", "SGD", "RMSprop"):
        if name == torch_name.lower():
            return getattr(th.optim, torch_name)
    raise ValueError(
        f"Unknown optimizer {optimizer_class!r}: use one of 'Adam', 'AdamW', 'SGD', 'RMSprop', 'RAD' "
        "or pass an optimizer class (e.g. optimizer_class=torch.optim.Adam)"
    )
