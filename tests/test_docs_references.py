"""Everything a user is pointed to is in the repository (issue 27): the README's and the docs'
links resolve to files of the repository, no reference leaves it (the project's specification
folder is not shipped), and every "contracts §N" in the README, the docs and ``recal ... --help``
is a section of docs/contracts.md."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from service.cli import COMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _sections() -> set[str]:
    return set(re.findall(r"^## (\d+)\.", (ROOT / "docs" / "contracts.md").read_text(), re.M))


def _cited(text: str) -> set[str]:
    """Section numbers of the contracts a text cites ("contracts §3", "contracts.md §1–§6")."""
    out = set()
    for span in re.findall(r"contracts(?:\.md)?\)?`?\)? ?((?:§\d+(?:\s*[–-]\s*§\d+)?(?:,\s*)?)+)", text):
        for a, b in re.findall(r"§(\d+)(?:\s*[–-]\s*§(\d+))?", span):
            out |= {str(n) for n in range(int(a), int(b or a) + 1)}
    return out


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_docs_point_only_inside_the_repository(path):
    text = path.read_text()
    assert "shared/spec" not in text, f"{path.name} points to the specification folder outside the repository"
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if re.match(r"[a-z]+://|mailto:", target):
            continue
        assert (path.parent / target).exists(), f"{path.name}: link to {target}, which is not in the repository"
    missing = _cited(text) - _sections()
    assert not missing, f"{path.name} cites contracts §{', §'.join(sorted(missing))}, not in docs/contracts.md"


@pytest.mark.parametrize("verb", sorted(COMMANDS))
def test_help_cites_the_repositorys_contracts(verb):
    parser = build_parser(verb)
    sub = next(a for a in parser._actions if a.dest == "verb")
    text = parser.format_help() + sub.choices[verb].format_help()
    flat = " ".join(text.split())
    assert "contracts §" not in flat.replace("docs/contracts.md §", ""), f"recal {verb} --help: {flat}"
    assert not (_cited(flat) - _sections())


def test_serve_help_names_the_service_section():
    parser = build_parser("serve")
    sub = next(a for a in parser._actions if a.dest == "verb")
    assert "docs/contracts.md §9" in " ".join(sub.choices["serve"].format_help().split())
    assert "9" in _sections() and (ROOT / "docs" / "service.md").exists()
