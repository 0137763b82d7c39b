"""The README as a user reads it: its Python example runs as written, it stays short, and no
commit hash appears in it or in a module docstring; module docstrings stay short."""

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MODULES = sorted((ROOT / "fsswarp").rglob("*.py"))
RUN_MARK = "<!-- test: run -->"
MAX_README_LINES = 250
MAX_DOCSTRING_LINES = 25
# 7 to 40 hex digits with at least one digit and one letter a-f: a short or full commit hash
# (plain numbers such as 20000 and words such as "deadbeef"-free prose are not matched).
HASH = re.compile(r"(?<![0-9A-Za-z_])(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![0-9A-Za-z_])")


def runnable_blocks(text: str) -> list[str]:
    """The fenced ```python blocks preceded by the ``<!-- test: run -->`` mark."""
    pattern = re.escape(RUN_MARK) + r"\s*\n```python\n(.*?)```"
    return re.findall(pattern, text, re.S)


def module_docstring(path: Path) -> str:
    return ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")), clean=False) or ""


def test_readme_python_example_runs_as_written(tmp_path):
    blocks = runnable_blocks(README.read_text(encoding="utf-8"))
    assert blocks, f"README.md has no ```python block marked {RUN_MARK}"
    script = tmp_path / "readme_example.py"
    script.write_text("\n".join(blocks), encoding="utf-8")
    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, f"the README example failed:\n{done.stdout}\n{done.stderr}"


def test_readme_is_short():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines (at most {MAX_README_LINES})"


def test_readme_links_resolve():
    text = README.read_text(encoding="utf-8")
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if re.match(r"[a-z]+://", target):
            continue
        assert (ROOT / target).exists(), f"README.md links to {target}, which does not exist"


def test_readme_has_no_commit_hash():
    text = README.read_text(encoding="utf-8")
    assert HASH.findall(text) == []


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_module_docstring_has_no_commit_hash(path):
    assert HASH.findall(module_docstring(path)) == []


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_module_docstring_is_short(path):
    lines = module_docstring(path).splitlines()
    assert len(lines) <= MAX_DOCSTRING_LINES, f"{len(lines)} lines (at most {MAX_DOCSTRING_LINES})"


def test_hash_pattern():
    assert HASH.findall("at d2c4478 and 567c664, commit 2f5f987a1b") == ["d2c4478", "567c664", "2f5f987a1b"]
    assert HASH.findall("20000 triangles, 0x05464444, 1e-3, cafebabe, deadbeef") == []
