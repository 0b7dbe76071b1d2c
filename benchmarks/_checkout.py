"""
Make the benchmark scripts import the ``sb3_dacerf`` of the repository they sit in.

``python benchmarks/<script>.py`` puts ``benchmarks/`` on ``sys.path``, not the repository root, so without this an
installed copy of the package (``pip install .`` copies it into site-packages) would be measured instead of the code
beside the script: edits would silently not take effect. The scripts import this module before the package.
Worker processes started with ``spawn`` inherit the parent's ``sys.path``.
"""

import sys
from pathlib import Path

#: The repository root (the folder holding ``sb3_dacerf/`` and ``benchmarks/``)
ROOT = Path(__file__).resolve().parents[1]

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
if "sb3_dacerf" in sys.modules and not Path(sys.modules["sb3_dacerf"].__file__ or "").resolve().is_relative_to(ROOT):
    raise ImportError(
        f"sb3_dacerf was imported from {sys.modules['sb3_dacerf'].__file__} before the benchmarks could import the "
        f"repository's copy in {ROOT}: import _checkout first (or install the repository with pip install -e .)"
    )
