import io
import logging
import sys

import pytest

from shared.logs import setup_logging


@pytest.fixture
def root_restored():
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def test_logs_follow_stderr_after_it_is_swapped_and_closed(monkeypatch, root_restored):
    first = io.StringIO()
    monkeypatch.setattr(sys, "stderr", first)
    setup_logging(service="tracker")
    logging.getLogger("trackgraph.test").warning("to the first stream")
    assert "[tracker] trackgraph.test: to the first stream" in first.getvalue()

    second = io.StringIO()
    monkeypatch.setattr(sys, "stderr", second)
    first.close()  # what a test runner does to the stream it captured with
    logging.getLogger("trackgraph.test").warning("to the second stream")
    assert "to the second stream" in second.getvalue()
    assert "Logging error" not in second.getvalue()


def test_verbosity_and_the_environment_choose_the_level(monkeypatch, root_restored):
    monkeypatch.delenv("TRACKGRAPH_LOG", raising=False)
    setup_logging(1)
    assert logging.getLogger().level == logging.DEBUG
    monkeypatch.setenv("TRACKGRAPH_LOG", "WARNING")
    setup_logging(1)
    assert logging.getLogger().level == logging.WARNING
    assert len(logging.getLogger().handlers) == 1
