"""The documentation names no path of the machine it was written on (a checkout, a home folder, a
cached environment): every Markdown file in the repository, docs and READMEs alike."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# absolute paths into a machine's own folders; example paths such as /tmp/lift-copy are fine
MACHINE_PATH = re.compile(r"(?<![\w.~-])/(?:work|root|home|Users|srv|mnt)/[\w.-]+")
SKIPPED = {".venv", "outputs", ".git", "node_modules", "build", "dist"}


def markdown_files() -> list[Path]:
    return sorted(p for p in ROOT.rglob("*.md") if not SKIPPED & set(p.relative_to(ROOT).parts))


def test_docs_name_no_machine_paths():
    files = markdown_files()
    assert {ROOT / "README.md", ROOT / "docs" / "real_robot.md", ROOT / "bench" / "README.md"} <= set(files)
    found = [
        f"{path.relative_to(ROOT)}:{n}: {match.group(0)}"
        for path in files
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), start=1)
        for match in MACHINE_PATH.finditer(line)
    ]
    assert found == []


def test_the_pattern_finds_what_it_should():
    assert MACHINE_PATH.search("+ /root/.cache/shiftkit/venv-b8cf/bin/python -m shiftkit")
    assert MACHINE_PATH.search("examples found in `/work/shared/data/vpace`")
    assert not MACHINE_PATH.search("shiftkit pull me/lift --root /tmp/lift-copy")
    assert not MACHINE_PATH.search("`~/.cache/shiftkit/deps-<hash>`, data/root/x, https://example.com/home/x")
