"""Small pieces shared by the algorithms of the package."""

from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import torch as th


@contextmanager
def frozen(parameters: Iterable[th.nn.Parameter]) -> Iterator[None]:
    """
    Stop gradients from reaching ``parameters`` inside the block (they still flow through them to the inputs),
    so that e.g. ``∇_a Q(s, a)`` costs no parameter gradients and the critic's ``.grad`` stays untouched.

    :param parameters: Parameters to freeze; those already frozen stay frozen afterwards
    """
    to_restore = [param for param in parameters if param.requires_grad]
    for param in to_restore:
        param.requires_grad_(False)
    try:
        yield
    finally:
        for param in to_restore:
            param.requires_grad_(True)
