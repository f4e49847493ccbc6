"""Every relative link in the README and the docs leads somewhere: the file (or folder) exists, and
a ``#anchor`` names a heading of the file it points into, as GitHub renders it (lower case,
punctuation dropped, each space a hyphen, a repeated heading ``-1``, ``-2``...). Links inside code
(fenced blocks, inline code) and links to other sites (``http:``, ``https:``, ``mailto:``) are not
followed. Read from the files; nothing is fetched."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

_FENCE = re.compile(r"^\s*(```|~~~)")
_CODE = re.compile(r"`+[^`]*`+")
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
_HTML_ID = re.compile(r"<a\s+(?:name|id)=\"([^\"]+)\"")
_EXTERNAL = ("http:", "https:", "mailto:", "ftp:")


def markdown_files() -> list[Path]:
    """The README and every page under docs/, in a stable order."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _prose(text: str) -> str:
    """``text`` with fenced code blocks blanked and inline code removed, line for line (a link's
    text may run over a line break)."""
    out, fenced = [], False
    for line in text.splitlines():
        if _FENCE.match(line):
            fenced = not fenced
            out.append("")
        else:
            out.append("" if fenced else _CODE.sub("", line))
    return "\n".join(out)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading's text: markup dropped, lower case, only letters, digits,
    ``-`` and ``_`` kept, each space a hyphen."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)     # a link's text
    text = re.sub(r"<[^>]+>", "", text).replace("`", "").replace("*", "")
    return "".join(c for c in text.lower() if c.isalnum() or c in " -_").replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor a link may name in ``path``: its headings' slugs (repeats numbered) and
    explicit ``<a name=...>`` / ``<a id=...>``."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    text = path.read_text(encoding="utf-8")
    out.update(_HTML_ID.findall(_prose(text)))
    fenced = False
    for line in text.splitlines():
        if _FENCE.match(line):
            fenced = not fenced
            continue
        m = None if fenced else _HEADING.match(line)
        if m:
            s = slug(m.group(2))
            n = seen.get(s, 0)
            seen[s] = n + 1
            out.add(s if n == 0 else f"{s}-{n}")
    return out


def broken_links(files: list[Path], root: Path = ROOT) -> list[str]:
    """``FILE:LINE: target: why`` for every relative link in ``files`` that leads nowhere."""
    cache: dict[Path, set[str]] = {}
    bad = []
    for f in files:
        prose = _prose(f.read_text(encoding="utf-8"))
        for m in _LINK.finditer(prose):
            target, no = m.group(1), prose.count("\n", 0, m.start(1)) + 1
            if target.startswith(_EXTERNAL):
                continue
            if not target:
                bad.append(f"{f.relative_to(root)}:{no}: (empty): a link to nowhere")
                continue
            where, _, anchor = target.partition("#")
            dest = (f.parent / where).resolve() if where else f
            name = f"{f.relative_to(root)}:{no}: {target}"
            if not dest.exists():
                bad.append(f"{name}: no such file")
            elif anchor and dest.suffix == ".md":
                if dest not in cache:
                    cache[dest] = anchors(dest)
                if anchor not in cache[dest]:
                    bad.append(f"{name}: no heading with that anchor in {dest.relative_to(root)}")
    return bad


def test_every_relative_link_in_the_readme_and_the_docs_leads_somewhere() -> None:
    files = markdown_files()
    assert len(files) > 10, "the docs were not found"
    bad = broken_links(files)
    assert not bad, "broken links:\n" + "\n".join(bad)


def test_the_check_finds_a_missing_file_and_a_missing_anchor(tmp_path: Path) -> None:
    (tmp_path / "a.md").write_text("# Top\n\n## The 2024 winner's code, and `ops`\n\nx\n\n## Top\n")
    (tmp_path / "b.md").write_text(
        "[ok](a.md#the-2024-winners-code-and-ops) [ok](a.md#top-1) [ok](#here) [site](https://x.y/#z)\n"
        "# Here\n[gone](c.md) [no anchor](a.md#nowhere) [over a line\nbreak](d.md) [empty]()\n"
        "```\n[in code](nothing.md)\n```\n`[inline](nothing.md)`\n")
    bad = broken_links([tmp_path / "b.md"], root=tmp_path)
    assert bad == ["b.md:3: c.md: no such file",
                   "b.md:3: a.md#nowhere: no heading with that anchor in a.md",
                   "b.md:4: d.md: no such file", "b.md:4: (empty): a link to nowhere"]
