"""Every relative link in README.md and docs/*.md points at a file that exists and, with a
`#fragment` into a Markdown file, at a heading of that file (GitHub's anchors)."""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,}).*?^ {0,3}\1[ \t]*$", re.S | re.M)
CODE_SPAN = re.compile(r"(`+)(?!`).+?(?<!`)\1(?!`)", re.S)
INLINE_LINK = re.compile(r"\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE = re.compile(r"^ {0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+\"[^\"]*\")?\s*$", re.M)
HTML_ANCHOR = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"", re.I)
HEADING = re.compile(r"^ {0,3}#{1,6}[ \t]+(.*?)[ \t]*#*[ \t]*$", re.M)
SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


def prose(text: str) -> str:
    """The text without fenced code blocks and code spans, where `[x](y)` is not a link."""
    return CODE_SPAN.sub("", FENCE.sub("", text))


def targets(text: str) -> Iterator[str]:
    """Every relative link target of a Markdown text (inline links, images, references)."""
    body = prose(text)
    for found in (*INLINE_LINK.findall(body), *REFERENCE.findall(body)):
        if not SCHEME.match(found):
            yield found


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: its text lowercased, punctuation dropped, spaces → `-`."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text only
    text = text.replace("`", "").replace("*", "")
    return re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")


def anchors(text: str) -> set[str]:
    """The anchors a Markdown page has: one per heading (`-1`, `-2` … for repeats), and
    explicit `<a id=…>` / `<a name=…>`."""
    found: set[str] = set(HTML_ANCHOR.findall(text))
    seen: dict[str, int] = {}
    for heading in HEADING.findall(FENCE.sub("", text)):
        base = slug(heading)
        count = seen.get(base, 0)
        seen[base] = count + 1
        found.add(base if count == 0 else f"{base}-{count}")
    return found


def broken(pages: Iterable[Path], root: Path) -> list[str]:
    """`page: target (why)` for each relative link that does not resolve inside `root`."""
    problems = []
    for page in pages:
        for target in targets(page.read_text()):
            path, _, fragment = target.partition("#")
            where = (page.parent / path).resolve() if path else page
            if path.startswith("/") or not where.is_relative_to(root):
                problems.append(f"{page.name}: {target} (outside the repository)")
            elif not where.exists():
                problems.append(f"{page.name}: {target} (no such file)")
            elif fragment and where.suffix == ".md" and fragment not in anchors(where.read_text()):
                problems.append(f"{page.name}: {target} (no such heading)")
    return problems


def test_every_relative_link_in_the_readme_and_docs_resolves() -> None:
    assert len(PAGES) > 15
    assert broken(PAGES, ROOT) == []


def test_the_check_finds_a_missing_file_a_missing_heading_and_skips_code(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    page = tmp_path / "docs" / "page.md"
    (tmp_path / "docs" / "other.md").write_text("# Other\n\n## The `[loop]` — scan task\n")
    page.write_text(
        "# Page\n\n## What happened?\n\n"
        "[ok](other.md#the-loop--scan-task) [up](../docs/other.md) [self](#what-happened)\n"
        "[gone](moved.md) [no heading](other.md#nowhere) [out](../../etc/passwd)\n"
        "[web](https://example.com/x.md) `[code](span.md)`\n\n"
        "```md\n[fenced](fenced.md)\n## Not a heading\n```\n\n"
        "[bad self](#not-a-heading)\n[ref]: missing.md\n"
    )
    assert broken([page], tmp_path) == [
        "page.md: moved.md (no such file)",
        "page.md: other.md#nowhere (no such heading)",
        "page.md: ../../etc/passwd (outside the repository)",
        "page.md: #not-a-heading (no such heading)",
        "page.md: missing.md (no such file)",
    ]


def test_anchors_follow_githubs_rules_for_code_punctuation_and_repeats() -> None:
    text = (
        "# Zenoh's threads (`bus.zenoh_threads`)\n## Keys (outside `machine/<id>`)\n"
        '## Notes\n## Notes\n<a id="here"></a>\n'
    )
    assert anchors(text) == {
        "zenohs-threads-buszenoh_threads",
        "keys-outside-machineid",
        "notes",
        "notes-1",
        "here",
    }
