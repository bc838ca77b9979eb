"""The user docs stay short and read as docs, not a development diary: docs/*.md and runtime/README.md
together hold at most 25,000 words, and none names a commit (a 7-40 character hex token with a digit and
a letter, outside fenced code blocks) or says "this round" / "the commit before". The history of the
figures lives in services/benchmarks/LOG.md, which is not checked here."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted((REPO_ROOT / "docs").glob("*.md")) + [REPO_ROOT / "runtime" / "README.md"]
MAX_WORDS = 25_000
COMMIT_LIKE = re.compile(r"\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b")
DIARY_PHRASES = ("this round", "the commit before")


def prose(text: str) -> str:
    """The page without its fenced code blocks (sha256 examples may legitimately sit there)."""
    return re.sub(r"^(```|~~~).*?^\1", "", text, flags=re.DOTALL | re.MULTILINE)


def test_the_pages_exist():
    assert len(PAGES) >= 10 and all(page.is_file() for page in PAGES)


def test_docs_hold_at_most_25000_words():
    words = {page.name: len(page.read_text(encoding="utf-8").split()) for page in PAGES}
    assert sum(words.values()) <= MAX_WORDS, f"{sum(words.values())} words: {words}"


@pytest.mark.parametrize("page", PAGES, ids=lambda page: str(page.relative_to(REPO_ROOT)))
def test_no_commit_hashes_or_diary_phrases(page):
    text = prose(page.read_text(encoding="utf-8"))
    hashes = sorted(set(COMMIT_LIKE.findall(text)))
    assert not hashes, f"{page.name} names commit-like tokens {hashes}"
    for phrase in DIARY_PHRASES:
        assert phrase not in text.lower(), f"{page.name} says {phrase!r}"


def test_the_checks_catch_what_they_are_for():
    assert COMMIT_LIKE.findall("measured against f054de1 and 7c42836")
    assert not COMMIT_LIKE.findall("deadbeef is all letters, 12345678 all digits, the 0x1f flag")
    assert not COMMIT_LIKE.findall(prose("text\n```sh\nsha256 3ace1ba0d148\n```\nmore"))
