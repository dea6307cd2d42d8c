"""The README and the documents under doc/ link only inside the repository, to files and headings that exist.

The README keeps what a ROS 2 user needs and links to the long documents under
``doc/``; this keeps those links (and the anchors into them) from breaking when
a section moves.
"""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "doc").glob("*.md"))]


def anchors(path: Path) -> set[str]:
    """The anchors GitHub gives the headings of ``path``: lower case, punctuation dropped, spaces as hyphens."""
    found: set[str] = set()
    in_code = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            in_code = not in_code
        match = re.match(r"#{1,6} (.+)", line)
        if in_code or not match:
            continue
        slug = re.sub(r"[^\w\- ]", "", match.group(1).strip().lower()).replace(" ", "-")
        anchor, n = slug, 0
        while anchor in found:
            n += 1
            anchor = f"{slug}-{n}"
        found.add(anchor)
    return found


def links(path: Path) -> list[str]:
    """Every link and image target of ``path``, outside code blocks and code spans."""
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)
    return re.findall(r"\]\(([^)\s]+)\)", text)


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda path: path.relative_to(ROOT).as_posix())
def test_links_stay_inside_the_repository_and_resolve(document):
    name = document.relative_to(ROOT).as_posix()
    for target in links(document):
        assert "://" not in target and not target.startswith("/"), f"{name} links outside the repository: {target}"
        file, _, anchor = target.partition("#")
        path = (document.parent / file).resolve() if file else document
        assert path.is_relative_to(ROOT), f"{name}: {target} leaves the repository"
        assert path.exists(), f"{name}: broken link {target}"
        if anchor and path.suffix == ".md":
            assert anchor in anchors(path), f"{name}: no heading for #{anchor} in {path.relative_to(ROOT)}"
