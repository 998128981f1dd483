import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
# copies of the project data (see tests/data/LICENSES.md): the tests run without ../shared beside the clone
DATA = REPO / "tests" / "data" / "volumes"


@pytest.fixture(autouse=True)
def _no_terminal_progress(monkeypatch):
    # Builds under test must stay quiet whatever terminal pytest runs in.
    monkeypatch.setenv("VOLPUZZLE_NO_PROGRESS", "1")


def pytest_configure():
    os.environ.setdefault("NUMBA_NUM_THREADS", "2")
