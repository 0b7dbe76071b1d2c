"""
Relative links of the Markdown files outside ``docs/`` (README, CONTRIBUTING, CHANGELOG, ``benchmarks/``,
``examples/``), as GitHub renders them: every linked file exists and every ``#anchor`` is a heading of its target. The
documentation under ``docs/`` is checked by its own build (``make docs`` fails on a broken reference).
"""

import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MARKDOWN_FILES = sorted(
    path
    for path in ROOT.rglob("*.md")
    if not any(part.startswith((".", "_")) or part in ("docs", "build", "dist") for part in path.relative_to(ROOT).parts[:-1])
    and not any(part.endswith(".egg-info") for part in path.relative_to(ROOT).parts)
)
FENCE = re.compile(r"^ {0,3}(```|~~~).*?^ {0,3}\1", re.M | re.S)
INLINE_CODE = re.compile(r"(`+).+?\1", re.S)
# [text](target) and [text](target "title"), the text possibly spread over lines, and [label]: target definitions
INLINE_LINK = re.compile(r"\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
DEFINITION = re.compile(r"^ {0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", re.M)
HEADING = re.compile(r"^ {0,3}#{1,6}\s+(.*?)\s*#*\s*$", re.M)


def without_code(text: str) -> str:
    """``text`` without its fenced code blocks and inline code, where brackets are not links."""
    return INLINE_CODE.sub("", FENCE.sub("", text))


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading: its text, lower case, without punctuation, spaces as hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text only
    text = re.sub(r"<[^>]+>", "", text).strip().lower()
    kept = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return kept.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Anchors of the headings of the Markdown file ``path``, with GitHub's ``-1``, ``-2``... for repeated ones."""
    found: set[str] = set()
    for heading in HEADING.findall(FENCE.sub("", path.read_text(encoding="utf-8"))):
        anchor, n = github_anchor(heading), 1
        while anchor in found:
            anchor, n = f"{github_anchor(heading)}-{n}", n + 1
        found.add(anchor)
    return found


def relative_links(path: Path) -> list[str]:
    """Targets of the links of ``path`` that point into the repository (no URL scheme, no ``mailto:``)."""
    text = without_code(path.read_text(encoding="utf-8"))
    targets = INLINE_LINK.findall(text) + DEFINITION.findall(text)
    return [target for target in targets if not re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target)]


def shown(path: Path) -> str:
    return str(path.relative_to(ROOT) if path.is_relative_to(ROOT) else path)


def broken_links(path: Path) -> list[str]:
    """The relative links of ``path`` whose file or heading does not exist, with the reason."""
    broken = []
    for target in relative_links(path):
        file_part, _, anchor = target.partition("#")
        linked = (path.parent / file_part).resolve() if file_part else path
        if not linked.exists():
            broken.append(f"{target}: no file {shown(linked)}")
        elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
            broken.append(f"{target}: no heading with the anchor #{anchor} in {shown(linked)}")
    return broken


def test_the_markdown_files_are_found():
    names = {str(path.relative_to(ROOT)) for path in MARKDOWN_FILES}
    assert {"README.md", "CONTRIBUTING.md", "CHANGELOG.md", "benchmarks/README.md", "benchmarks/learning.md"} <= names
    assert not any(name.startswith("docs/") for name in names)


def test_the_checker_finds_a_dead_file_and_a_dead_anchor(tmp_path):
    (tmp_path / "target.md").write_text("# A heading, with `code`\n\n## A heading, with `code`\n")
    page = tmp_path / "page.md"
    page.write_text(
        "[ok](target.md#a-heading-with-code) [repeated](target.md#a-heading-with-code-1) [missing](missing.md)\n"
        "[bad anchor](target.md#no-such-heading) `[in code](missing.md)` [web](https://example.com/x.md)\n"
        "```\n[in a fence](missing.md)\n```\n[label]: target.md#nor-this\n"
    )
    broken = broken_links(page)
    assert len(broken) == 3, broken
    assert broken[0].startswith("missing.md: no file") and "#no-such-heading" in broken[1] and "#nor-this" in broken[2]


@pytest.mark.parametrize("path", MARKDOWN_FILES, ids=lambda path: str(path.relative_to(ROOT)))
def test_relative_links_resolve(path):
    broken = broken_links(path)
    assert not broken, f"dead links in {path.relative_to(ROOT)} (fix the target or the link):\n" + "\n".join(broken)
