"""The suite's own scheduling: the files it starts first are files of the suite."""

from __future__ import annotations

from pathlib import Path

from conftest import LONGEST_FILES


def test_every_file_started_first_exists():
    """A renamed file would silently lose its place at the front (and the parallel part its
    balance): the list names only files that are here, each once."""
    here = {path.name for path in Path(__file__).parent.glob("test_*.py")}
    assert sorted(set(LONGEST_FILES) - here) == []
    assert len(set(LONGEST_FILES)) == len(LONGEST_FILES)
