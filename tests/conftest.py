"""
The expensive runs that tests of several modules read, made once per session (read them, never modify them: copy a
folder before changing it), and how the suite shares two cores under pytest-xdist (``bash run.sh test`` runs it with
``-n auto --maxprocesses 2 --dist loadfile --no-loadscope-reorder``).
"""

import json
import os
from pathlib import Path

import pytest
import torch as th

from tests.shared_runs import TINY_WALKER_RUN


def pytest_configure(config):
    """An xdist worker uses one thread (torch's and its subprocesses' OpenMP): two workers on two cores would
    otherwise run four."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = "1"
        th.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    """
    Under xdist (``--dist loadfile --no-loadscope-reorder``: each file on one worker, the files in this order): the
    tiny reproduction's own file first, so that one worker makes it (minutes) while the other runs the files that do
    not read it; the other files that read it last, their readers after their other tests, so that no worker waits
    for it while there is other work.
    """
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    files = list(dict.fromkeys(item.path for item in items))
    readers = {item.path for item in items if "tiny_reproduction" in item.fixturenames}

    def order(item):
        reads = "tiny_reproduction" in item.fixturenames
        rank = 0 if item.path.name == "test_reproduce.py" else 2 if item.path in readers else 1
        return rank, files.index(item.path), rank == 2 and reads

    items.sort(key=order)  # stable: in collection order within each key


def shared_by_the_workers(tmp_path_factory, name: str, make):
    """
    ``make(folder)`` once per session: under xdist the first worker to ask makes it in a folder shared by the
    workers (under a file lock); the others wait for it and get what it returned.

    :param name: the folder's name, in the session's base temporary folder
    :param make: ``folder -> JSON-able result``
    :return: what ``make`` returned
    """
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return make(tmp_path_factory.getbasetemp() / name)
    from filelock import FileLock  # torch's own dependency

    root = tmp_path_factory.getbasetemp().parent  # the session's, above each worker's popen-gwN
    with FileLock(str(root / f"{name}.lock")):
        done = root / f"{name}.json"
        if not done.exists():  # the first worker: make it; a worker whose make raised left no file
            done.write_text(json.dumps(make(root / name)))
        return json.loads(done.read_text())


@pytest.fixture(scope="session")
def tiny_walker_run(tmp_path_factory):
    """
    A real tiny training run through :func:`sb3_collapse.run.runner.train`: :data:`tests.shared_runs.TINY_WALKER_RUN`
    (walker-walk, 800 frames = 40 agent steps at action repeat 20, 48x48, evaluated every 400 frames, snapshots on),
    in the folder ``walker-walk_s0`` of the logdir ``<tmp_path_factory's base>/tiny_walker_run``.

    :return: the run's :class:`~sb3_collapse.run.runner.TrainResult`
    """
    from sb3_collapse.run.config import TrainConfig
    from sb3_collapse.run.runner import train

    threads = th.get_num_threads()  # the run sets torch's threads (torch_threads=1): the tests keep theirs
    try:
        return train(TrainConfig(**TINY_WALKER_RUN, logdir=str(tmp_path_factory.getbasetemp() / "tiny_walker_run")))
    finally:
        th.set_num_threads(threads)


@pytest.fixture(scope="session")
def tiny_reproduction(tmp_path_factory):
    """
    ``python -m sb3_collapse.reproduce --scale tiny`` run once (every stage: the sweep, the transplant grid, the probe,
    the films and the report at CPU sizes), in the folder ``tiny_reproduction`` of the session's base temporary
    folder (shared by xdist's workers: :func:`shared_by_the_workers`; read it, never modify it).

    :return: ``(out, exit status, its output)``
    """
    import contextlib
    import io
    import time

    from sb3_collapse.commands.reproduce import main

    def reproduce(out):
        threads, printed = th.get_num_threads(), io.StringIO()
        start = time.perf_counter()
        try:
            with contextlib.redirect_stdout(printed):
                status = main(["--out", str(out), "--scale", "tiny", "--no-progress-bar"])
        finally:
            th.set_num_threads(threads)
        print(f"tiny reproduction: {time.perf_counter() - start:.1f} s")
        return str(out), status, printed.getvalue()

    out, status, printed = shared_by_the_workers(tmp_path_factory, "tiny_reproduction", reproduce)
    return Path(out), status, printed
