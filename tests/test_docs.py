"""The documentation the code cites: every section reference resolves, no path leaves the repo."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
METHODS_DOC = ROOT / "docs" / "methods.md"

# A heading that opens a section: "## §1", "### §2.4 The EKF (Yu §3)" -> "1", "2.4".
_HEADING = re.compile(r"^#{1,6}\s+§(\d+(?:\.\d+)*)\b", re.MULTILINE)
# A citation and the run of section numbers after it: "methods.md §1.7 and §2.5",
# "methods.md §1.6, §5.5", "methods.md §2.1–2.4". Only the first is required to carry "§".
_CITATION = re.compile(
    r"(?:METHODS|methods\.md) (§\d+(?:\.\d+)*(?:\s*(?:–|-|,|and)\s*§?\d+(?:\.\d+)*)*)"
)
_NUMBER = re.compile(r"\d+(?:\.\d+)*")
# Built in two pieces so that this file does not contain what it searches for.
_OUTSIDE = ("../" + "shared", "/work/" + "shared")


def methods_sections(text: str) -> set[str]:
    """Section numbers of the headings of a methods document ("0", "1.6", ...)."""
    return set(_HEADING.findall(text))


def cited_sections(text: str) -> list[str]:
    """Every section number cited as "methods.md §x" or "methods.md §x" in ``text``."""
    return [n for run in _CITATION.findall(text) for n in _NUMBER.findall(run)]


def tracked_files() -> list[Path]:
    try:
        out = subprocess.run(
            ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=30
        ).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        pytest.skip(f"not a git checkout: {exc}")
    return [ROOT / name for name in out.decode().split("\0") if name]


def test_parsers_on_known_text() -> None:
    doc = "# Title\n## §0 Conventions\n### §1.6 J-ICP (Li §2.3.2)\ntext §9.9\n#### §10.2 x\n"
    assert methods_sections(doc) == {"0", "1.6", "10.2"}
    text = (
        '"""(methods.md §1.7 and §2.5) ... methods.md §2.1–2.4) ... (methods.md §1.6, §5.5).\n'
        "methods.md §3. Next sentence 4.5; METHODS = (1, 2) and METHODS Y1\n"
    )
    assert cited_sections(text) == ["1.7", "2.5", "2.1", "2.4", "1.6", "5.5", "3"]


def test_methods_document_numbers_its_sections() -> None:
    sections = methods_sections(METHODS_DOC.read_text(encoding="utf-8"))
    # The numbering the code's citations were written against, kept so they can be repointed.
    required = {"0", "1", "2", "3", "4"} | {f"1.{i}" for i in range(1, 8)}
    required |= {f"2.{i}" for i in range(1, 6)}
    assert required <= sections, sorted(required - sections)


def test_every_citation_in_src_names_an_existing_section() -> None:
    sections = methods_sections(METHODS_DOC.read_text(encoding="utf-8"))
    missing = []
    n_citations = 0
    for path in sorted((ROOT / "src").rglob("*.py")):
        for number in cited_sections(path.read_text(encoding="utf-8")):
            n_citations += 1
            if number not in sections:
                missing.append(f"{path.relative_to(ROOT)}: §{number}")
    assert n_citations > 50, f"only {n_citations} citations found: the pattern is broken"
    assert not missing, missing


def test_no_tracked_file_points_outside_the_repository() -> None:
    offenders = []
    for path in tracked_files():
        if not path.is_file():
            continue  # deleted in the working tree, not yet committed
        data = path.read_bytes()
        offenders += [f"{path.relative_to(ROOT)}: {s}" for s in _OUTSIDE if s.encode() in data]
    assert not offenders, offenders
