"""Shared fixtures: a real Zenoh router on a free loopback port and clients of it.

Everything stays on 127.0.0.1 with ports picked at run time; multicast scouting is off; every
session opened here is closed by its fixture.  Helpers that tests import (``free_port``,
``wait_for``, ``running_service``, ...) live in tests/support.py.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import zenoh

from service.transport.session import ZenohOptions, open_session
from tests.support import zenoh_router


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tests marked ``slow`` first, each group in its collected order: with a file's tests
    handed to one process (``--dist loadfile`` in the Makefile) the files that hold them go
    first, and the two test processes end on short ones instead of one finishing a long file
    alone.  A stable sort: every process collects the same order."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture
def router() -> Iterator[str]:
    """A router-mode Zenoh session on a free loopback port; yields its endpoint."""
    with zenoh_router() as endpoint:
        yield endpoint


@pytest.fixture
def client(router: str) -> Iterator[zenoh.Session]:
    session = open_session(ZenohOptions(mode="client", connect=(router,)))
    try:
        yield session
    finally:
        session.close()
