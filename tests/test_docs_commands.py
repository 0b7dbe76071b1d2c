"""
The commands of the README and of the guide pages (``docs/guide/*.md``) run as written, in the order a reader meets
them, from a copy of the repository's working files.

Every fenced ``bash`` and ``python`` block of a page runs, page by page, in one directory per page: the bash blocks
one command at a time (``\\``-continued lines joined, comments dropped), the python blocks as scripts. What is changed
before a command runs is listed here and nowhere else:

- ``python -m pip install ...`` (the set-up) is left out of a command: the test environment has every extra;
- ``SHORTER``: exact replacements that shorten a training or evaluation budget (each must occur in its page, so the
  table cannot outlive the text it shortens);
- ``NOT_RUN``: commands that are not run here, with the reason;
- ``KNOWN_FAILURES``: commands that fail today, with the bug they hit: run, and tolerated either way (remove the entry
  when the bug is fixed, so that the command is checked again).
"""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUIDE_ORDER = ["install", "quickstart", "rl_zoo", "export", "data_regime"]  # the toctree's order; others follow by name
PAGES = ["README.md"] + [
    str(path.relative_to(ROOT))
    for path in sorted(
        (ROOT / "docs" / "guide").glob("*.md"),
        key=lambda path: (GUIDE_ORDER.index(path.stem) if path.stem in GUIDE_ORDER else len(GUIDE_ORDER), path.stem),
    )
]
# What a page's commands read from the repository (the rest of it they do not touch)
COPIED = ["examples", "benchmarks", "hyperparams", "docs"]
LINKED = ["sb3_dacerf", "setup.py", "setup.cfg", "pyproject.toml", "Makefile", "sb3_dacerf_zoo_hook.py"]

ZOO_SHORT = " -n 300 -params learning_starts:100"
SHORTER: dict[str, list[tuple[str, str]]] = {
    "README.md": [
        ("python examples/quickstart.py", "python examples/quickstart.py --timesteps 300 --eval-episodes 1"),
        (".learn(20_000, progress_bar=True)", ".learn(300, progress_bar=True)"),
        ("--episodes 5", "--episodes 1"),
    ],
    "docs/guide/install.md": [
        ("python examples/quickstart.py", "python examples/quickstart.py --timesteps 300 --eval-episodes 1"),
    ],
    "docs/guide/quickstart.md": [
        (".learn(20_000, progress_bar=True)", ".learn(300, progress_bar=True)"),
    ],
    "docs/guide/rl_zoo.md": [
        (
            "--num-threads 1 --eval-freq 10000 --save-freq 50000 -P -tb runs",
            "--num-threads 1 --eval-freq 300 --eval-episodes 1 --save-freq 300 -P -tb runs" + ZOO_SHORT,
        ),
        (
            "--num-threads 1 -i logs/dacerf/DMC-humanoid-stand-v0_1/DMC-humanoid-stand-v0.zip",
            "--num-threads 1 -i logs/dacerf/DMC-humanoid-stand-v0_1/DMC-humanoid-stand-v0.zip" + ZOO_SHORT,
        ),
        ("-f logs --no-render", "-f logs --no-render -n 50"),
        ("-f logs -n 1000", "-f logs -n 20"),
        (
            "--algo sac --env DMC-humanoid-stand-v0 --num-threads 1",
            "--algo sac --env DMC-humanoid-stand-v0 --num-threads 1" + ZOO_SHORT,
        ),
        (
            "--algo dacerf --env DACERF-Intersection-v0 --num-threads 1",
            "--algo dacerf --env DACERF-Intersection-v0 --num-threads 1" + ZOO_SHORT,
        ),
        (
            "-params callback:\"'rl_zoo3.callbacks.ParallelTrainCallback'\"",
            "-n 300 -params learning_starts:100 callback:\"'rl_zoo3.callbacks.ParallelTrainCallback'\"",
        ),
        ("-optimize -n 100000 --n-trials 20", "-optimize -n 300 --n-trials 1 --eval-episodes 1 -params learning_starts:100"),
    ],
    "docs/guide/export.md": [
        ("python examples/quickstart.py", "python examples/quickstart.py --timesteps 300 --eval-episodes 1"),
    ],
    "docs/guide/data_regime.md": [
        (
            "--timesteps 200000 --steps-per-gradient 20 --n-envs 2",
            "--timesteps 400 --learning-starts 100 --eval-episodes 1 --steps-per-gradient 20 --n-envs 2",
        ),
        (
            "--steps-per-gradient 20 \\\n    --timesteps 200000 --eval-freq 10000 --checkpoint-freq 10000",
            "--steps-per-gradient 20 --seeds 1 --eval-episodes 1 \\\n    --timesteps 400 --eval-freq 200 --checkpoint-freq 200",
        ),
        ("--variants dacerf sac --report-only", "--variants dacerf sac --seeds 1 --report-only"),
    ],
}
NOT_RUN = {
    "make check": "the test suite itself, with the lint, type and docs checks (CI runs it)",
    "python -m sphinx -W --keep-going -b html docs docs/_build/html": "the documentation build, which make check runs",
}
KNOWN_FAILURES: dict[str, str] = {}
FENCE = re.compile(r"^```(bash|python)[^\n]*\n(.*?)^```", re.M | re.S)


def blocks(text: str) -> list[tuple[str, str]]:
    """The fenced bash and python blocks of a Markdown text, in order: (language, code)."""
    return FENCE.findall(text)


def bash_commands(code: str) -> list[str]:
    """The commands of a bash block: continued lines joined, comments and the pip set-up left out."""
    commands = []
    for line in re.sub(r"\s*\\\n\s*", " ", code).splitlines():
        line = re.sub(r"(^|\s)#.*$", "", line).strip()  # a comment (no command here has a # inside quotes)
        parts = [part.strip() for part in line.split("&&")]
        parts = [part for part in parts if part and not part.startswith("python -m pip install")]
        if parts:
            commands.append(" && ".join(parts))
    return commands


def shortened(page: str, text: str) -> str:
    for old, new in SHORTER.get(page, []):
        assert old in text, f"{page} no longer contains {old!r}: update SHORTER in {Path(__file__).name}"
        text = text.replace(old, new)
    return text


def test_the_pages_are_found_and_the_extraction_works():
    assert PAGES[:3] == ["README.md", "docs/guide/install.md", "docs/guide/quickstart.md"]
    code = 'python -m pip install x && python a.py  # comment\n# only a comment\npython b.py \\\n    --flag "#x"\n'
    assert bash_commands(code) == ["python a.py", 'python b.py --flag "#x"']
    assert blocks("```bash\necho 1\n```\n```yaml\nx: 1\n```\n```python\nprint(1)\n```\n") == [
        ("bash", "echo 1\n"),
        ("python", "print(1)\n"),
    ]


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES)
def test_the_commands_of_a_page_run(page, tmp_path):
    for name in COPIED:
        shutil.copytree(
            ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("_build", "_generated", "runs", "checkpoints")
        )
    for name in LINKED:
        (tmp_path / name).symlink_to(ROOT / name)
    # The repository's package, one torch thread (as the pages advise), no display
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])  # `python` is this interpreter
    env = {**os.environ, "PATH": path, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    text = shortened(page, (ROOT / page).read_text(encoding="utf-8"))
    ran = 0
    for index, (language, code) in enumerate(blocks(text)):
        if language == "python":
            script = tmp_path / f"block_{index}.py"
            script.write_text(code, encoding="utf-8")
            commands = [f"python {script.name}"]
        else:
            commands = bash_commands(code)
        for command in commands:
            if any(command.startswith(skipped) or command == skipped for skipped in NOT_RUN):
                continue
            known = next((bug for marker, bug in KNOWN_FAILURES.items() if marker in command), None)
            result = subprocess.run(
                ["bash", "-c", command], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600, check=False
            )
            ran += 1
            if known:
                continue
            assert result.returncode == 0, (
                f"{page}: `{command}` failed (exit {result.returncode}):\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
            )
    assert ran > 0, f"no command of {page} ran"
