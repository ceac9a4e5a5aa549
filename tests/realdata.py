"""Where tests find the real third-party recordings, and what they do when absent.

The files live outside the repository, at ``<project root>/../shared/realdata/`` (see its
README). Without them a test that needs them is skipped with a message saying where it
looked; with ``SURFPHASE_REQUIRE_REALDATA=1`` (set in CI, which has ``../shared``) it
fails instead, so CI can never pass by skipping them.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
REQUIRE_ENV = "SURFPHASE_REQUIRE_REALDATA"


def require_realdata() -> bool:
    """True when the environment demands the real files (``SURFPHASE_REQUIRE_REALDATA=1``)."""
    return os.environ.get(REQUIRE_ENV, "").strip().lower() in ("1", "true", "yes")


def realdata(*parts: str) -> Path:
    """The path ``REALDATA/<parts...>``; skip the test (fail it when required) if absent."""
    path = REALDATA.joinpath(*parts)
    if not path.exists():
        msg = f"real recording {path} not found (the shared test data is not beside the project)"
        if require_realdata():
            pytest.fail(f"{msg}; {REQUIRE_ENV}=1 requires it", pytrace=False)
        pytest.skip(f"{msg}; set {REQUIRE_ENV}=1 to make this a failure")
    return path
