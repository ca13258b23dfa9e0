"""Shared test fixtures: the one session-scoped Prefect test harness (opt-in, not autouse)."""

from __future__ import annotations

import os

import pytest

# Offline and quiet, before anything imports Prefect.
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")


@pytest.fixture(scope="session")
def prefect_harness():
    """A temporary Prefect server and database for the whole session (≈11 s once).

    Yields the API URL, so subprocesses can reuse the server instead of starting their own.
    """
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield PREFECT_API_URL.value()


def in_ci() -> bool:
    """`CI=true` (what CI systems set): promised checks must run, never skip."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def require_tool(names: tuple[str, ...], install: str) -> str:
    """The first of `names` on PATH. Missing: a skip on a developer machine, a failure under CI
    (the README's test command installs it, so a missing tool means that step broke)."""
    import shutil

    found = next((p for p in map(shutil.which, names) if p), None)
    if found is not None:
        return found
    message = f"{names[0]} not installed ({install})"
    if in_ci():
        pytest.fail(f"{message}; CI=true, so this promised check fails instead of skipping",
                    pytrace=False)
    pytest.skip(message)


CHROMIUM_INSTALL = "apt-get update && apt-get install -y chromium"
PDFLATEX_INSTALL = "apt-get install -y texlive-latex-base texlive-latex-recommended"


@pytest.fixture
def chromium() -> str:
    return require_tool(("chromium", "chromium-browser"), CHROMIUM_INSTALL)


@pytest.fixture
def pdflatex() -> str:
    return require_tool(("pdflatex",), PDFLATEX_INSTALL)
