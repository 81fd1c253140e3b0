"""Docstrings and comments say what a thing does and why; measurements, commit hashes and session history stay out.

Figures measured in one run go stale the day they are written: they belong in docs/perf-log.md (dated, machine
named) or in a commit message. Every module of the package is parsed: module, class and function docstrings with
``ast``, comments with ``tokenize``; string literals that are not docstrings and code are not scanned, so hex
constants and unit conversions in code never trip the check. Each hit is reported as ``file:line: text``.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "aerial_loc_env"

# A standalone word of 7-40 hex digits holding at least one digit and one letter a-f: what a commit hash looks like.
COMMIT_HASH = re.compile(r"(?<![\w.-])(?=[0-9a-fA-F]*[0-9])(?=[0-9a-fA-F]*[a-fA-F])[0-9a-fA-F]{7,40}(?![\w-])")
# A millisecond or microsecond figure, a range ("0.4-0.5 ms") included.
TIME_FIGURE = re.compile(r"\b\d+(?:\.\d+)?(?:\s?[-\u2013]\s?\d+(?:\.\d+)?)?\s?(?:ms|us|\u00b5s)\b")
SESSION_HISTORY = re.compile(r"\b(?:this session|next session|the lead(?:'s)?)\b", re.IGNORECASE)

# Hex words that are legitimately in a docstring or comment (file formats' magics and the like); none so far.
HEX_ALLOWED: frozenset[str] = frozenset()

CHECKS = (
    ("commit hash", COMMIT_HASH),
    ("time figure", TIME_FIGURE),
    ("session history", SESSION_HISTORY),
)


def _docstrings(tree: ast.Module) -> Iterator[tuple[int, str]]:
    """(first line, text) of the module's, every class's and every function's docstring."""
    for node in ast.walk(tree):
        if not isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        body = node.body
        if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                and isinstance(body[0].value.value, str):
            yield body[0].value.lineno, body[0].value.value


def _comments(source: str) -> Iterator[tuple[int, str]]:
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            yield tok.start[0], tok.string


def prose(path: Path) -> Iterator[tuple[int, str]]:
    """(line, text) of every line of the file's docstrings and comments."""
    source = path.read_text(encoding="utf-8")
    for first, text in _docstrings(ast.parse(source, str(path))):
        for offset, line in enumerate(text.splitlines()):
            yield first + offset, line
    yield from _comments(source)


def hits(path: Path, root: Path = REPO) -> list[str]:
    """``file:line: kind 'match' in: text`` for every forbidden token in the file's docstrings and comments."""
    rel = path.relative_to(root).as_posix()
    found = []
    for line_no, line in prose(path):
        for kind, pattern in CHECKS:
            for m in pattern.finditer(line):
                if kind == "commit hash" and m.group(0).lower() in HEX_ALLOWED:
                    continue
                found.append(f"{rel}:{line_no}: {kind} {m.group(0)!r} in: {line.strip()}")
    return sorted(set(found), key=lambda s: (s.split(":")[0], int(s.split(":")[1])))


def test_docstrings_and_comments_hold_no_measurements_hashes_or_session_history():
    modules = sorted(PACKAGE.rglob("*.py"))
    assert len(modules) > 50  # the walk found the package
    found = [h for path in modules for h in hits(path)]
    for h in found:
        print(h)
    assert not found, (
        f"{len(found)} measurement(s), commit hash(es) or session history in docstrings/comments "
        "(move figures to docs/perf-log.md, hashes and history to commit messages):\n" + "\n".join(found)
    )


@pytest.mark.parametrize(
    ("text", "kind"),
    [
        ("# 0.47 -> 0.19 ms a frame", "time figure"),
        ("# 0.4-0.5 ms each", "time figure"),
        ("# about 12 us per call", "time figure"),
        ("# 3\u00b5s", "time figure"),
        ("# the variant of 57ad3e6 is gone", "commit hash"),
        ("# see 57ad3e6f0b1c2d3e4f5a6b7c8d9e0f1a2b3c4d5e.", "commit hash"),
        ("# measured in this session", "session history"),
        ("# next session, same VM", "session history"),
        ("# the lead's measurements", "session history"),
    ],
)
def test_the_checks_catch_what_they_are_for(tmp_path, text, kind):
    mod = tmp_path / "mod.py"
    mod.write_text(f'"""Doc."""\n\nx = 1  {text}\n', encoding="utf-8")
    found = [k for _, line in prose(mod) for k, p in CHECKS if p.search(line)]
    assert found == [kind]


@pytest.mark.parametrize(
    "text",
    [
        "# x = 0xdeadbeef1 in code is not read; nor is facade, decade, accede or 1000000",
        "# the leading edge; a session-level cache; 3 msgs; 5 users; 20 mm; 2 ms_per_frame",
        "# 0x7f3a2b1c as a literal in a comment is a hex constant, not a hash",
        "# shape (1234567, 2); seeds 0-19; 1e-13 rad",
    ],
)
def test_the_checks_pass_ordinary_prose(tmp_path, text):
    mod = tmp_path / "mod.py"
    mod.write_text(f'"""Doc."""\n\nx = 1  {text}\n', encoding="utf-8")
    assert [line for _, line in prose(mod) if any(p.search(line) for _, p in CHECKS)] == []


def test_code_and_plain_strings_are_not_scanned(tmp_path):
    mod = tmp_path / "mod.py"
    mod.write_text('"""Doc."""\n\nMAGIC = "5f3a9c1"\nDELAY = "5 ms"\n', encoding="utf-8")
    assert [line for _, line in prose(mod)] == ["Doc."]


def test_a_hit_is_reported_as_file_and_line(tmp_path):
    pkg = tmp_path / "aerial_loc_env"
    pkg.mkdir()
    mod = pkg / "mod.py"
    mod.write_text('"""Doc.\n\nFaster since 57ad3e6.\n"""\n\nx = 1  # 2.5 ms\n', encoding="utf-8")
    assert hits(mod, root=tmp_path) == [
        "aerial_loc_env/mod.py:3: commit hash '57ad3e6' in: Faster since 57ad3e6.",
        "aerial_loc_env/mod.py:6: time figure '2.5 ms' in: # 2.5 ms",
    ]
