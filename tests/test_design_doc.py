"""The design notes the code cites live in the repository, and nothing cites an issue tracker.

Every "DESIGN N" / "DESIGN N.M" / "DESIGN 5.3d" reference in the repository's .py, .md,
.ipynb and .yaml files (outside ``.venv``, hidden folders, ``results/paper``,
``docs/design.md`` itself and this file) must name a numbered heading of ``docs/design.md``
(``## 3. ...``, ``### 5.3 ...``, ``#### 5.3d ...``); a quoted title after a reference
(``DESIGN 3, "Decisions at a known budget"``, ``docs/design.md, "..."``) must be in one of
that section's headings. Code, tests, benchmarks, notebooks and the README carry no
issue-tracker numbers: the history belongs in commit messages, and the text says what, not
which ticket.
"""

import json
import os
import re
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "design.md"
CITING_SUFFIXES = {".py", ".md", ".ipynb", ".yaml"}
EXCLUDED = {Path("results/paper"), Path("docs/design.md"),
            Path("tests/test_design_doc.py")}  # this file: its bad references are test data
ISSUE_FREE = ("drake_cert", "systems", "synthesis", "tests", "benchmarks", "notebooks",
              "README.md")
ISSUE_SUFFIXES = {".py", ".md", ".ipynb", ".yaml", ".txt", ".toml", ".cfg"}

SECTION = r"\d+(?:\.\d+)?[a-z]?\b"
REFERENCE = re.compile(rf"\bDESIGN\s+(?:sections?\s+)?({SECTION})"
                       rf"((?:\s*(?:,|-|and)\s*{SECTION})*)")
TITLED = re.compile(r'(?:\bDESIGN\s+(?:sections?\s+)?(\d+(?:\.\d+)?[a-z]?)|docs/design\.md)'
                    r'[^"]{0,4}"([^"]+)"')
HEADING = re.compile(r"^#{2,4}\s+(\d+(?:\.\d+)?[a-z]?)\.?\s+(.*)$", re.MULTILINE)
ISSUE = re.compile(r"\b[Ii]ssues?\s*#?\s*\d+"        # issue 7, issues 8, issue #12
                   r"|\b[Ii]ssue[ _]item\b"           # "issue item 7"
                   r"|(?<![A-Za-z])[Ii]ssue_\d+"       # a test named test_issue_9_...
                   r"|(?<![&\w])#\d{1,4}\b"           # #19 (not &#39; nor a #a1b2c3 colour)
                   r"|\bDone[-]when\b")               # an issue's acceptance list


def _pruned(name: str) -> bool:
    """Folders never scanned: hidden ones (.venv, .git, caches), build output, data caches."""
    return name.startswith(".") or name.endswith(".egg-info") or name in ("data_cache",
                                                                          "__pycache__")


def _files(tops: tuple[str, ...] | None, suffixes: set[str]) -> list[Path]:
    """Text files under ``tops`` (relative to the repository; None: all of it) with one of
    ``suffixes``, without descending into pruned or excluded folders."""
    found = []
    for top in [ROOT / t for t in tops] if tops else [ROOT]:
        if top.is_file():
            found += [top] if top.suffix in suffixes else []
            continue
        for folder, dirs, names in os.walk(top):
            here = Path(folder)
            dirs[:] = sorted(d for d in dirs if not _pruned(d)
                             and (here / d).relative_to(ROOT) not in EXCLUDED)
            found += [here / n for n in sorted(names) if Path(n).suffix in suffixes
                      and (here / n).relative_to(ROOT) not in EXCLUDED]
    return found


def text_of(path: Path) -> str:
    """A file's text; for a notebook, its cells' sources (outputs are regenerated)."""
    raw = path.read_text(encoding="utf-8", errors="replace")
    if path.suffix != ".ipynb":
        return raw
    cells = json.loads(raw)["cells"]
    return "\n".join("".join(c["source"]) if isinstance(c["source"], list) else c["source"]
                     for c in cells)


@cache
def headings() -> dict[str, str]:
    """Section number -> heading title of docs/design.md."""
    return {number: title for number, title in HEADING.findall(DOC.read_text())}


def referenced_sections(text: str) -> list[str]:
    """Every section a text cites; ``DESIGN 2-3`` and ``DESIGN sections 4-5`` cite each
    section of the range, ``DESIGN 5, 6`` and ``DESIGN 3 and 6`` both."""
    cited = []
    for first, rest in REFERENCE.findall(text):
        items = [first] + re.findall(SECTION, rest)
        if "-" in rest and len(items) == 2 and all(i.isdigit() for i in items):
            cited += [str(n) for n in range(int(items[0]), int(items[1]) + 1)]
        else:
            cited += items
    return cited


def unresolved(text: str, sections: dict[str, str]) -> list[str]:
    """References in ``text`` that name no heading (or a quoted title no heading of that
    section holds), as readable strings; empty when all resolve."""
    bad = [f"DESIGN {s}" for s in referenced_sections(text) if s not in sections]
    flat = " ".join(text.split())
    for number, title in TITLED.findall(flat):
        wanted = " ".join(title.split()).lower()
        scope = [t for n, t in sections.items()  # the section and its subsections
                 if not number or n == number or n.startswith(number + ".")
                 or re.fullmatch(re.escape(number) + "[a-z]", n)]
        if not any(wanted in t.lower() for t in scope):
            bad.append(f'{"DESIGN " + number if number else "docs/design.md"}, "{title}"')
    return bad


def issue_references(text: str) -> list[str]:
    return [m.group(0) for m in ISSUE.finditer(text)]


def test_design_notes_have_the_seven_numbered_sections_once_each():
    numbers = HEADING.findall(DOC.read_text())
    names = [n for n, _ in numbers]
    assert len(names) == len(set(names)), "a section number is used twice"
    assert {str(i) for i in range(1, 8)} <= set(names)
    assert "DESIGN N" in DOC.read_text()[:600], "the top must say what DESIGN N means"


def test_every_design_reference_in_the_repository_names_a_heading_of_the_design_notes():
    sections = headings()
    problems, count = [], 0
    for path in _files(None, CITING_SUFFIXES):
        text = text_of(path)
        count += len(referenced_sections(text))
        problems += [f"{path.relative_to(ROOT)}: {b}" for b in unresolved(text, sections)]
    assert count > 50, f"only {count} references found: the scan is not reading the code"
    assert not problems, "references that resolve to no heading of docs/design.md:\n" + \
        "\n".join(problems)


def test_a_reference_to_a_missing_section_or_title_is_reported():
    sections = headings()
    good = ("(DESIGN 5.3d) and (DESIGN sections 4-5), DESIGN 3 and 6, DESIGN 5, 6;\n"
            '(DESIGN 3, "Decisions at a\n known budget")')
    assert unresolved(good, sections) == []
    assert referenced_sections(good) == ["5.3d", "4", "5", "3", "6", "5", "6", "3"]
    assert unresolved("see DESIGN " + "9.2 for it", sections) == ["DESIGN 9.2"]
    assert unresolved("(DESIGN 5.3" + "z)", sections) == ["DESIGN 5.3z"]
    assert unresolved("DESIGN 9-" + "11", sections) == ["DESIGN 11"]
    assert unresolved('DESIGN 4, "' + 'Decisions at a known budget"', sections) != []
    assert unresolved('(docs/design.md, "' + 'No such heading")', sections) != []


def test_no_issue_numbers_remain_in_code_tests_benchmarks_notebooks_or_readme():
    problems = []
    for path in _files(ISSUE_FREE, ISSUE_SUFFIXES):
        for hit in issue_references(text_of(path)):
            problems.append(f"{path.relative_to(ROOT)}: {hit!r}")
    assert not problems, "issue-tracker references (say what, not which issue):\n" + \
        "\n".join(problems)


def test_the_issue_check_catches_the_usual_forms_and_spares_look_alikes():
    word = "iss" + "ue"
    for text in (f"({word} 7, item 5)", f"{word.capitalize()} #12", f"{word}s 8",
                 "fixed in #" + "19", f"({word} item 7)", f"def test_{word}_9_x():",
                 "the " + "Done" + "-when list"):
        assert issue_references(text), text
    for text in ("colour #1f77b4", "&#39;", "an issue of units", "#include <x>",
                 "# 5 Hz camera", "x[#]"):
        assert issue_references(text) == [], text
