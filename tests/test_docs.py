"""The user docs' shape: ``docs/`` holds docs and their images only, each doc at most 300 lines and naming no issue,
every relative link of the README and the docs resolves, and the README's results table stays a table one reads."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DOCS = REPO / "docs"
IMAGES = (".png", ".gif", ".jpg", ".svg", ".mp4")
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)\s]*)?\)")


def user_docs() -> list[Path]:
    return [REPO / "README.md", *sorted(DOCS.glob("*.md"))]


def test_docs_hold_docs_and_their_images_only() -> None:
    others = [p.relative_to(REPO).as_posix() for p in DOCS.rglob("*") if p.is_file()
              and not (p.parent == DOCS and p.suffix == ".md") and not (p.suffix in IMAGES and "images" in p.parts)]
    assert not others, f"{others}: scripts and results go to lab/, images to docs/images/"


def test_each_doc_is_at_most_300_lines_and_names_no_issue() -> None:
    for doc in sorted(DOCS.glob("*.md")):
        lines = doc.read_text().splitlines()
        assert len(lines) <= 300, f"{doc.name}: {len(lines)} lines (split a long reference into pages)"
    for doc in user_docs():
        found = re.findall(r"\bissues? \d+", doc.read_text())
        assert not found, f"{doc.name} names {found}: a user doc says what, not which issue"


def slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(doc: Path) -> set[str]:
    return {slug(line.lstrip("#")) for line in doc.read_text().splitlines() if line.startswith("#")}


def untracked(path: Path) -> bool:
    """Whether ``path`` is a file on this disk that a clone would lack (ignored or never added): a link to it passes
    here and fails on a fresh clone. Outside a git checkout (an unpacked sdist) nothing counts as untracked."""
    if not (REPO / ".git").exists() or not path.is_file():
        return False
    listed = subprocess.run(["git", "ls-files", "--error-unmatch", str(path)], cwd=REPO, capture_output=True)
    return listed.returncode != 0


def test_every_relative_link_and_anchor_resolves() -> None:
    """The README's, the docs' and the lab's own pages' links, and the anchors they name, in a fresh clone: a link to
    a file that is here but untracked (a drawn figure) is broken there (the lab's notebook keeps links to result
    folders since removed: git has them)."""
    for doc in [*user_docs(), *sorted((REPO / "lab").glob("*.md"))]:
        for target, anchor in re.findall(r"\]\(([^)\s#]*)(?:#([^)\s]*))?\)", doc.read_text()):
            if re.match(r"^[a-z]+:", target):
                continue
            path = doc.parent / target if target else doc
            assert path.exists() and not untracked(path), f"{doc.name}: {target} is not in a clone"
            if anchor and path.suffix == ".md":
                assert anchor in anchors(path), f"{doc.name}: {target}#{anchor}"


def test_the_readme_results_table_is_short_and_links_every_row() -> None:
    text = (REPO / "README.md").read_text()
    section = text[text.index("## Results"):]
    section = section[: section.index("\n## ")]
    rows = [line for line in section.splitlines() if line.startswith("|")][2:]  # (less the header and its rule)
    assert 1 <= len(rows) <= 12, f"{len(rows)} rows"
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert max(len(c.split()) for c in cells) <= 25, row
        assert LINK.search(cells[-1]), f"no doc linked: {row}"
    assert text.count("`make test` takes") == 1
