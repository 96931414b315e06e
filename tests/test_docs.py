"""The documentation a user reads: short enough to read, its links resolve, and it says what things
are rather than when they were tried (the API reference itself is built by ``make docs``)."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# A diary's words: "stop 27", "issue 13" mean nothing to a reader of the repository.
DIARY = re.compile(r"\b(stop|issue) [0-9]+", re.IGNORECASE)


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _prose(path: Path) -> str:
    return re.sub(r"```.*?```", "", path.read_text(), flags=re.S)


def test_readme_and_usv_guide_stay_short():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150
    assert len((ROOT / "docs" / "usv.md").read_text().splitlines()) <= 300


def test_readme_starts_with_the_two_commands():
    lines = (ROOT / "README.md").read_text().splitlines()
    block = lines[lines.index("```") + 1 :][:2]
    assert [line.split("#")[0].strip() for line in block] == ["make demo", "make test"]


@pytest.mark.parametrize("folder", ["README.md", "docs", "diffgcl", "experiments"])
def test_no_diary_words(folder):
    paths = [ROOT / folder] if folder.endswith(".md") else (ROOT / folder).rglob("*")
    found = [
        f"{path.relative_to(ROOT)}:{n}: {line.strip()}"
        for path in paths
        if path.suffix in (".md", ".py", ".yaml") and ".venv" not in path.parts
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if DIARY.search(line)
    ]
    assert not found, "\n".join(found)


def test_relative_links_and_anchors_resolve():
    anchors = {
        path: {_slug(h) for h in re.findall(r"^#+ (.*)$", _prose(path), re.M)} for path in DOCS
    }
    broken = []
    for path in DOCS:
        for link in re.findall(r"\]\(([^)\s]+)\)", _prose(path)):
            if link.startswith(("http://", "https://")):
                continue
            target, _, anchor = link.partition("#")
            resolved = (path.parent / target).resolve() if target else path
            if not resolved.exists():
                broken.append(f"{path.name}: {link} (no such file)")
            elif anchor and resolved.suffix == ".md" and anchor not in anchors[resolved]:
                broken.append(f"{path.name}: {link} (no such heading)")
    assert not broken, "\n".join(broken)
