"""The shared loopback server for tests that do not change its configuration."""

from collections.abc import Iterator

import pytest
from loopback import ServerThread, running_server


@pytest.fixture(scope="module")
def server() -> Iterator[ServerThread]:
    with running_server() as thread:
        yield thread
