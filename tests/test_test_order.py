"""The suite's own scheduling: every file named in conftest's longest-first list exists, so a
renamed file cannot drop out of the list unnoticed (it would run in its alphabetical place)."""
from pathlib import Path

from tests.conftest import LONGEST_FILES


def test_every_longest_file_exists_once():
    here = Path(__file__).parent
    assert len(set(LONGEST_FILES)) == len(LONGEST_FILES)
    assert [name for name in LONGEST_FILES if not (here / name).is_file()] == []
