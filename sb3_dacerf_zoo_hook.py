"""
Start-up hook that makes ``python -m rl_zoo3.train --algo dacerf ...`` (and ``--algo dacer``) work with no wrapper script.

``pip install`` puts ``sb3_dacerf_zoo.pth`` (Python <= 3.14) and ``sb3_dacerf_zoo.start`` (PEP 829, Python >= 3.15)
in site-packages; both call :func:`install` at interpreter start. That only adds a finder to ``sys.meta_path``
and imports nothing: when RL Zoo's ``utils``, ``hyperparams_opt``, ``exp_manager`` or ``callbacks`` module has been
executed, :func:`sb3_dacerf.zoo.register` adds DACERF, DACER and DSAC to it (and, with ``rl_zoo3.utils``, gives
them one PyTorch thread unless the command line has ``--num-threads``). Set ``SB3_DACERF_NO_ZOO_HOOK=1`` to turn the
hook off.
"""

import os
import sys

# Runs in every interpreter start: import nothing that site.py has not imported already
TYPE_CHECKING = False
if TYPE_CHECKING:
    from importlib.machinery import ModuleSpec
    from types import ModuleType
    from typing import Any

ZOO_MODULES = frozenset({"rl_zoo3.utils", "rl_zoo3.hyperparams_opt", "rl_zoo3.exp_manager", "rl_zoo3.callbacks"})


class _RegisteringLoader:
    """Runs the module with its own loader, then lets ``sb3_dacerf.zoo`` register DACERF, DACER and DSAC in it."""

    def __init__(self, loader: "Any") -> None:
        self.loader = loader

    def create_module(self, spec: "ModuleSpec") -> "ModuleType | None":
        return self.loader.create_module(spec)

    def exec_module(self, module: "ModuleType") -> None:
        self.loader.exec_module(module)
        # A broken sb3_dacerf must not break RL Zoo for the other algorithms
        try:
            from sb3_dacerf.zoo import register

            register(module)
        except Exception as error:
            import warnings

            warnings.warn(f"sb3_dacerf could not register DACERF with RL Zoo ({module.__name__}): {error!r}", stacklevel=2)

    def __getattr__(self, name: str) -> "Any":
        # get_source, get_filename, ... for tracebacks and inspect
        return getattr(self.loader, name)


class ZooFinder:
    """Meta path finder that wraps the loader of the RL Zoo modules in ``ZOO_MODULES``."""

    @classmethod
    def find_spec(cls, fullname: str, path: "Any" = None, target: "ModuleType | None" = None) -> "ModuleSpec | None":
        if fullname not in ZOO_MODULES:
            return None
        for finder in sys.meta_path:
            find_spec = getattr(finder, "find_spec", None)
            if finder is cls or find_spec is None:
                continue
            spec = find_spec(fullname, path, target)
            if spec is not None and spec.loader is not None:
                spec.loader = _RegisteringLoader(spec.loader)
                return spec
        return None


def install() -> None:
    """Put :class:`ZooFinder` first on ``sys.meta_path`` (idempotent)."""
    if os.environ.get("SB3_DACERF_NO_ZOO_HOOK") != "1" and ZooFinder not in sys.meta_path:
        sys.meta_path.insert(0, ZooFinder)
