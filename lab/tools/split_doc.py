"""Split a long user doc into pages at its ``##`` sections, rewriting anchors across the pages and the other docs.

    python lab/tools/split_doc.py docs/physics.md physics-running.md:"Commanded actuation" ...

Each ``PAGE:"HEADING PREFIX"`` starts a new page at the first ``## `` heading that begins with the prefix; the page
runs to the next split. Links ``(#anchor)`` and ``(doc.md#anchor)`` in docs/ and README.md follow their section.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path


def slug(heading: str) -> str:
    text = heading.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def main(doc: str, splits: list[str]) -> None:
    path = Path(doc)
    lines = path.read_text().splitlines(keepends=True)
    starts = []
    for spec in splits:
        page, prefix = spec.split(":", 1)
        at = next(i for i, line in enumerate(lines) if line.startswith("## " + prefix))
        starts.append((at, page))
    starts.sort()
    pages = [(path.name, 0, starts[0][0])] + [(p, a, b) for (a, p), (b, _) in
                                              zip(starts, [*starts[1:], (len(lines), None)], strict=True)]
    where = {}
    for name, a, b in pages:
        for line in lines[a:b]:
            if line.startswith("#"):
                where[slug(line.lstrip("#"))] = name
    texts = {name: "".join(lines[a:b]) for name, a, b in pages}

    def fix(text: str, here: str) -> str:
        def local(m: re.Match) -> str:
            page = where.get(m.group(1))
            return m.group(0) if page in (None, here) else f"]({page}#{m.group(1)})"

        text = re.sub(r"\]\(#([^)\s]+)\)", local, text)

        def other(m: re.Match) -> str:
            page = where.get(m.group(2))
            if page is None:
                return m.group(0)
            return f"]({m.group(1)}{'' if page == here else page}#{m.group(2)})" if page != here else f"](#{m.group(2)})"

        return re.sub(r"\]\(((?:\.\./)*(?:docs/)?)" + re.escape(path.name) + r"#([^)\s]+)\)",
                      lambda m: f"]({m.group(1)}{where.get(m.group(2), path.name)}#{m.group(2)})"
                      if where.get(m.group(2), path.name) != here or m.group(1) else f"](#{m.group(2)})", text)

    for name, text in texts.items():
        (path.parent / name).write_text(fix(text, name))
    for other in [*path.parent.glob("*.md"), Path("README.md")]:
        if other.name in texts:
            continue
        other.write_text(fix(other.read_text(), other.name))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
