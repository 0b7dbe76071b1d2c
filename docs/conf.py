"""Sphinx configuration of the sb3_dacerf documentation (Markdown pages through MyST, API pages through autodoc)."""

import os
import sys
from pathlib import Path

# Document the sources of this checkout, not an installed copy
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
# One torch thread while autodoc imports the package, like everything else on a small machine
os.environ.setdefault("OMP_NUM_THREADS", "1")

from sb3_dacerf.version import __version__  # noqa: E402

project = "sb3_dacerf"
author = "sb3_dacerf contributors"
copyright = "2026, sb3_dacerf contributors"
version = __version__
release = __version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]

# MyST: ``(label)=`` targets, $math$, ::: fences, heading anchors for [text](page.md#anchor) links
myst_enable_extensions = ["colon_fence", "dollarmath", "deflist"]
myst_heading_anchors = 3

# autodoc: SB3-style ``:param:`` docstrings, signatures as written, members in source order
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_description_target = "documented_params"
autodoc_default_options = {"show-inheritance": True}
autodoc_preserve_defaults = True

html_theme = "furo" if __import__("importlib").util.find_spec("furo") else "alabaster"
html_title = f"sb3_dacerf {__version__}"
html_static_path: list[str] = []


# ---------------------------------------------------------------------------------------------------------------------
# Tables generated from the code, so that they cannot drift from it: written to _generated/ (not a page of its own)
# and included by the pages that show them.
GENERATED = Path(__file__).resolve().parent / "_generated"
exclude_patterns.append("_generated")


def _markdown_cell(value: object) -> str:
    return "`" + repr(value).replace("|", "\\|") + "`"


def _driving_config_table() -> str:
    """Every config key of the two driving environments: its default in each and the values its check accepts."""
    from sb3_dacerf.envs.driving.intersection import IntersectionEnv
    from sb3_dacerf.envs.driving.multilane import MultilaneEnv

    multilane, intersection = MultilaneEnv.default_config(), IntersectionEnv.default_config()
    rules = {**IntersectionEnv.config_rules(), **MultilaneEnv.config_rules()}
    lines = [
        "| key | `DACERF-Multilane-v0` | `DACERF-Intersection-v0` | accepted values |",
        "|---|---|---|---|",
    ]
    for key in sorted(set(multilane) | set(intersection)):
        # A rule returns None for a valid value and what it expects otherwise: ask it about a value no rule accepts
        expected = rules[key](object()) or ""
        cells = [_markdown_cell(config[key]) if key in config else "—" for config in (multilane, intersection)]
        lines.append(f"| `{key}` | {cells[0]} | {cells[1]} | {expected.replace('|', chr(92) + '|')} |")
    return "\n".join(lines) + "\n"


def _dmc_ids() -> str:
    """The registered DMC ids, one row per domain."""
    from sb3_dacerf.envs.dmc import DMC_TASKS

    tasks: dict[str, list[str]] = {}
    for domain, task in DMC_TASKS:
        tasks.setdefault(domain, []).append(task)
    lines = ["| domain | ids |", "|---|---|"]
    for domain, names in tasks.items():
        lines.append(f"| {domain} | " + ", ".join(f"`DMC-{domain}-{task}-v0`" for task in names) + " |")
    return "\n".join(lines) + "\n"


def _write_generated() -> None:
    GENERATED.mkdir(exist_ok=True)
    for name, text in {"driving_config.md": _driving_config_table(), "dmc_ids.md": _dmc_ids()}.items():
        path = GENERATED / name
        if not path.exists() or path.read_text(encoding="utf-8") != text:  # unchanged files keep Sphinx's cache valid
            path.write_text(text, encoding="utf-8")


_write_generated()
