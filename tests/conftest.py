import shutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"


@pytest.fixture
def config_copy(tmp_path) -> Path:
    """A writable copy of the shipped configs/ tree."""
    dst = tmp_path / "configs"
    shutil.copytree(CONFIGS, dst)
    return dst
