"""The service as users meet it: ``flyscan serve --sim`` in its own process, on loopback."""
import pytest

from running import FAST_PASS, RunningService


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    running = RunningService(tmp_path_factory.mktemp("service") / "data", env=FAST_PASS)
    yield running
    running.stop()
