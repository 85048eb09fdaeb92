"""The guides read well in the built site: sections are headings (they make the table of
contents), and code comments do not run off behind a scroll bar at 1280 px."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: characters of a code line that fit the content column of the site at 1280 px (material
#: theme: 61rem grid less both sidebars; code at 0.85 x 0.8rem, about 0.6 em per character)
CODE_COLUMNS = 84


def _pages():
    skip = {"results", "api", "gen"}
    return [p for p in sorted((ROOT / "docs").rglob("*.md"))
            if not skip & set(p.relative_to(ROOT / "docs").parts)]


def _outside_code(text: str):
    in_code = False
    for number, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            in_code = not in_code
            continue
        if not in_code:
            yield number, line


def test_sections_are_headings_not_bold_sentences():
    found = []
    for page in _pages():
        lines = page.read_text(encoding="utf-8").splitlines()
        for number, line in _outside_code("\n".join(lines)):
            before = lines[number - 2] if number > 1 else ""
            if not before.strip() and re.match(r"\*\*[^*]{1,60}[.?]\*\*", line):
                found.append(f"{page.relative_to(ROOT)}:{number}: {line[:50]}")
    assert len(_pages()) > 20 and not found, found


def test_code_comments_fit_the_page():
    long = []
    for page in _pages():
        text = page.read_text(encoding="utf-8")
        for m in re.finditer(r"^```(bash|python|toml|sh)[^\n]*\n(.*?)^```", text, re.S | re.M):
            for line in m.group(2).splitlines():
                if len(line) > CODE_COLUMNS and re.search(r"(^|\s)# ", line):
                    long.append(f"{page.relative_to(ROOT)}: {line[:60]}... ({len(line)})")
    assert not long, long


def _changes_page() -> str:
    return (ROOT / "docs" / "changes.md").read_text(encoding="utf-8")


def test_changes_page_lists_every_moved_module():
    """The 'What changed' page's table of moved modules is hsiffc/_moved.py's, row for row: a
    path moved later and not listed (or listed wrongly) fails here."""
    from hsiffc._moved import MOVED

    rows = dict(re.findall(r"^\| `(hsiffc[\w.]*)` \| `(hsiffc[\w.]*)` \|$", _changes_page(), re.M))
    assert rows == MOVED, {"missing or wrong": {k: v for k, v in MOVED.items()
                                                if rows.get(k) != v},
                           "not moved": sorted(set(rows) - set(MOVED))}


def test_changes_page_new_spellings_run(tmp_path):
    """The page's block of new spellings runs as written, in a fresh interpreter (the old
    path's warning shows only on its first import in a process)."""
    blocks = re.findall(r"^```python\n(.*?)^```", _changes_page(), re.S | re.M)
    assert len(blocks) == 1
    proc = subprocess.run([sys.executable, "-c", blocks[0]], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
