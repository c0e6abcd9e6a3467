"""Engine tests of mosiv-genesis: marked ``genesis_engine`` (and ``slow``), they run when the
Genesis engine (genesis-world) is installed. Without it they are deselected, never skipped in
silence: pytest's summary counts them as "deselected" and a line after collection and at the
end of the run names them and says what to install (with pytest-xdist the workers pass them on
and the controller prints them at the end: the repository's conftest.py). Everything that only
reads a Genesis recording runs on the committed scene in tests/data and needs no engine."""

from __future__ import annotations

import importlib.util

import pytest

ENGINE_INSTALLED = importlib.util.find_spec("genesis") is not None
REASON = "the Genesis engine is not installed (pip install 'mosiv-genesis[engine]')"
_DESELECTED = pytest.StashKey[list]()


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "genesis_engine: needs the Genesis engine; deselected when it is not installed"
    )
    config.addinivalue_line("markers", "slow: takes minutes on a CPU")


def pytest_collection_modifyitems(config, items):
    if ENGINE_INSTALLED:
        return
    engine = [item for item in items if item.get_closest_marker("genesis_engine")]
    if engine:
        items[:] = [item for item in items if not item.get_closest_marker("genesis_engine")]
        config.hook.pytest_deselected(items=engine)
        config.stash[_DESELECTED] = [item.nodeid for item in engine]
        if hasattr(config, "workeroutput"):  # a pytest-xdist worker: the controller prints them
            config.workeroutput["mosiv_notices"] = _notice(config)


def _notice(config) -> list[str]:
    names = config.stash.get(_DESELECTED, [])
    if not names:
        return []
    return [f"mosiv-genesis: {len(names)} engine test(s) deselected: {REASON}"] + [
        f"  deselected {n}" for n in names
    ]


def pytest_report_collectionfinish(config, start_path, items):
    return _notice(config)[:1]


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    for line in _notice(config):
        terminalreporter.write_line(line, yellow=True)
