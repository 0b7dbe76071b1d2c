"""Optimizer look-up by name, so RL Zoo YAML files and ``policy_kwargs`` can say ``optimizer_class="RAD"``."""

import torch as th

RAD_INSTALL_HINT = "pip install pytorch-rad  (or: pip install 'sb3_dacerf[rad]')"


def get_optimizer_class(optimizer_class: type[th.optim.Optimizer] | str) -> type[th.optim.Optimizer]:
    """
    Resolve an optimizer given as a class or by name.

    Names are case-insensitive: ``"Adam"``, ``"AdamW"``, ``"SGD"``, ``"RMSprop"`` (from ``torch.optim``)
    and ``"RAD"``, the relativistic adaptive gradient descent of the DACER-F paper, taken from the
    authors' ``pytorch-rad`` package (an optional dependency).

    :param optimizer_class: An optimizer class (returned unchanged) or its name
    :return: The optimizer class
    """
    if not isinstance(optimizer_class, str):
        return optimizer_class
    name = optimizer_class.lower()
    if name == "rad":
        try:
            from rad.optim import RAD
        except ImportError as error:
            raise ImportError(f"The RAD optimizer needs the pytorch-rad package: {RAD_INSTALL_HINT}") from error
        return RAD
    torch_optimizers = {cls.lower(): getattr(th.optim, cls) for cls in ("Adam", "AdamW", "SGD", "RMSprop")}
    if name not in torch_optimizers:
        raise ValueError(
            f"Unknown optimizer {optimizer_class!r}: use one of 'Adam', 'AdamW', 'SGD', 'RMSprop', 'RAD' "
            "or pass an optimizer class (e.g. optimizer_class=torch.optim.Adam)"
        )
    return torch_optimizers[name]
