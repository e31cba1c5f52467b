"""Shared test helpers: where the real recordings live (../shared/data beside the checkout)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def data_path(relative: str) -> Path:
    """Path of a real recording under ../shared/data. CI has the directory, so a missing file FAILS the test
    when CI=true (a silently skipped accuracy test would hide a broken checkout); elsewhere it skips."""
    path = DATA / relative
    if not path.is_file():
        if os.environ.get("CI") == "true":
            pytest.fail(f"{path} is missing; with CI=true the shared recordings must be beside the checkout")
        pytest.skip(f"{path} is not available")
    return path
