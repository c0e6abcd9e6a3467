"""The whole suite (core and plugins) on several processes with pytest-xdist.

pyproject's ``addopts`` run ``python -m pytest`` with ``-n auto --dist loadgroup``: one worker
per CPU core (``-n 0`` runs everything in this process, and ``--pdb`` does so by itself).

- **Units of work.** A test module goes to one worker as a whole, so its module-scoped fixtures
  (the diagnosis runs, the fuzz recipes' scene, ...) are built once. GROUPS below join the
  tests under a path into one unit; so does an ``xdist_group`` mark where pytest-xdist still
  can (its ``--dist loadgroup`` marks a test's node id, which pytest 9.2 no longer lets it
  change: pytest-xdist issue 1386). The groups are handed out first (GROUPS in their order),
  then the modules, largest first (counted in tests): so the first workers each start on a
  group, in a fresh process.
- **Threads.** Each worker runs torch, OpenMP and Taichi's CPU backend on its share of the
  cores (one thread with ``-n auto``): the workers already keep every core busy, and two of
  them with a thread per core each would oversubscribe the cores, which torch's thread pool
  takes badly. Warp's CPU kernels use one thread anyway. ``OMP_NUM_THREADS`` set by hand wins.
- **Reports.** xdist's controller collects nothing, so it never hears of the tests the workers
  deselect (``-m``, ``-k``, a conftest's ``pytest_collection_modifyitems``); the workers pass
  them on, and the summary counts them as a run in one process does. A conftest's lines for the
  end of the run (see plugins/mosiv-genesis/tests/conftest.py) travel the same way, in
  ``config.workeroutput[NOTICES]``: the controller prints them once, after the summary.
"""

from __future__ import annotations

import os

import pytest

#: key of config.workeroutput: lines a worker's conftest wants printed at the end of the run
NOTICES = "mosiv_notices"
_DESELECTED = "mosiv_deselected"
_RELAYED = pytest.StashKey[list]()

#: units of work larger than a module, (start of the node ids, group name), handed out in this
#: order before everything else: the longest first, so that they run side by side
GROUPS = (
    # Taichi's offline cache keys a kernel by the fields made before it in the process: run in
    # the same order from a fresh process, the backend's tests and the parity suite find their
    # kernels in the cache every run (spread over the workers, they compiled them again)
    ("plugins/mosiv-taichi-mpm/tests/", "mosiv-taichi-mpm"),
    ("tests/test_parity.py::", "parity"),
    # one module, the longest after those (its three diagnosis fixtures): started early, it
    # cannot end the run late
    ("tests/test_diagnose.py::", "diagnose"),
    # the tiny scene and its fit: session fixtures of mosiv-gauss's conftest, made once
    ("plugins/mosiv-gauss/tests/test_dynamic_", "mosiv-gauss-tiny-scene"),
)


#: xdist's scheduler methods that ModuleOrGroupScheduling overrides
_PRIVATE_SCHEDULER_API = ("_split_scope", "_assign_work_unit")


def _on_worker(config) -> bool:
    return hasattr(config, "workerinput")


def pytest_configure(config):
    config.stash[_RELAYED] = []
    if not _on_worker(config):
        return
    # the cores shared out between the workers (one each on CI's two); set before torch, Taichi
    # or a subprocess starts a thread pool, and torch's own as it may be imported already
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    threads = str(max(1, (cores or 1) // max(1, workers)))
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "TI_CPU_MAX_NUM_THREADS"):
        os.environ.setdefault(name, threads)
    import torch

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


# ------------------------------------------------------------------------------ scheduling
@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    # the hooks below override two private methods of xdist's scheduler: where a release has
    # changed them, its own --dist loadgroup runs (slower, never wrong)
    if not all(hasattr(LoadGroupScheduling, name) for name in _PRIVATE_SCHEDULER_API):
        return None

    class ModuleOrGroupScheduling(LoadGroupScheduling):
        """``--dist loadgroup`` with GROUPS, whose other tests go by module (``--dist
        loadfile``), and whose groups are handed out before the modules."""

        def __init__(self, config, log=None) -> None:
            super().__init__(config, log)
            self.groups: set[str] = set()

        def _split_scope(self, nodeid: str) -> str:
            group = super()._split_scope(nodeid)  # an xdist_group mark's, or the node id
            if group == nodeid:
                group = next((name for start, name in GROUPS if nodeid.startswith(start)), None)
                if group is None:
                    return nodeid.split("::", 1)[0]
            self.groups.add(group)
            return group

        def _assign_work_unit(self, node) -> None:
            # GROUPS in their order, then other groups, then the modules (the workqueue is in
            # order of size): move the unit to hand out to the front
            if not hasattr(self, "workqueue"):
                return super()._assign_work_unit(node)
            rank = {name: i for i, (_, name) in enumerate(GROUPS)}
            waiting = [scope for scope in self.workqueue if scope in self.groups]
            if waiting:
                first = min(waiting, key=lambda scope: rank.get(scope, len(GROUPS)))
                self.workqueue.move_to_end(first, last=False)
            super()._assign_work_unit(node)

    return ModuleOrGroupScheduling(config, log)


# ------------------------------------------------------------------------------- reports
def pytest_deselected(items):
    config = getattr(items[0], "config", None) if items else None  # node ids on the controller
    if config is not None and _on_worker(config):
        config.workeroutput.setdefault(_DESELECTED, []).extend(item.nodeid for item in items)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """Take the deselections and notices of the first worker to finish (all collect alike)."""
    output = getattr(node, "workeroutput", None)
    if not output or "exitstatus" not in output or node.config.stash[_RELAYED]:
        return
    node.config.stash[_RELAYED] = [*output.get(NOTICES, []), None]  # None: relayed already
    if output.get(_DESELECTED):
        # the terminal reporter only counts what it is given: node ids stand in for the items
        node.config.hook.pytest_deselected(items=list(output[_DESELECTED]))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    for line in config.stash.get(_RELAYED, []):
        if line is not None:
            terminalreporter.write_line(line, yellow=True)
