"""Every relative link in the README and docs/ resolves: the file exists, and an anchor names a
heading of the page it points to (GitHub's rule: lower case, punctuation dropped, spaces to
hyphens)."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def anchors(page: Path) -> set[str]:
    """The anchors GitHub gives the page's headings."""
    out, fenced = set(), False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        if fenced or not line.startswith("#"):
            continue
        title = line.lstrip("#").strip().lower()
        slug = re.sub(r"[^\w\- ]", "", title).replace(" ", "-")
        out.add(slug)
    return out


def links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # not inside code blocks
    text = re.sub(r"`[^`\n]*`", "", text)  # nor inside inline code
    return [t for t in LINK.findall(text) if not re.match(r"[a-z]+:", t)]


def test_the_pages_have_links_to_check():
    assert sum(len(links(p)) for p in PAGES) >= 5


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_and_anchor_resolves(page):
    broken = []
    for target in links(page):
        path, _, anchor = target.partition("#")
        where = (page.parent / path).resolve() if path else page
        if not where.exists():
            broken.append(f"{target}: no file {where.relative_to(ROOT)}")
        elif anchor and where.suffix == ".md" and anchor not in anchors(where):
            broken.append(f"{target}: no heading #{anchor} in {where.relative_to(ROOT)}")
    assert not broken, "\n".join(broken)


def test_the_checker_sees_a_broken_anchor(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# A title, with punctuation!\n\n[ok](#a-title-with-punctuation) "
                    "[bad](#no-such-heading) [file](missing.md)\n")
    assert "a-title-with-punctuation" in anchors(page)
    assert links(page) == ["#a-title-with-punctuation", "#no-such-heading", "missing.md"]


def test_the_readme_is_a_front_page():
    """At most 15,000 bytes: what and why, the two commands, the vehicle workflow, the Python
    example, the headline and links; the rest lives in docs/."""
    size = len((ROOT / "README.md").read_bytes())
    assert size <= 15_000, f"README.md is {size:,} bytes: move detail into docs/"
    for name in ("usage", "commands", "results", "design"):
        assert f"](docs/{name}.md)" in (ROOT / "README.md").read_text(), name
