"""The service as users meet it: ``flyscan serve --sim`` in its own process, on loopback."""
import pytest

from running import FAST_PASS, TOKEN, RunningService


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    running = RunningService(tmp_path_factory.mktemp("service") / "data", env=FAST_PASS)
    yield running
    running.stop()


@pytest.fixture(scope="module")
def guarded(tmp_path_factory):
    """A service with a token (``running.TOKEN``) that also guards its reads."""
    running = RunningService(tmp_path_factory.mktemp("guarded") / "data",
                             env={**FAST_PASS, "FLYSCAN_TOKEN": TOKEN,
                                  "FLYSCAN_PROTECT_READS": "true", "FLYSCAN_BODY_IDLE_S": "3"})
    yield running
    running.stop()
