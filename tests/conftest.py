"""
The expensive runs that tests of several modules read, made once per session (read them, never modify them: copy a
folder before changing it).
"""

import pytest
import torch as th

from tests.shared_runs import TINY_WALKER_RUN


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
    the films and the report at CPU sizes), in ``<tmp_path_factory's base>/tiny_reproduction`` (read it, never
    modify it).

    :return: ``(out, exit status, its output)``
    """
    import contextlib
    import io
    import time

    from sb3_collapse.commands.reproduce import main

    out = tmp_path_factory.getbasetemp() / "tiny_reproduction"
    threads, printed = th.get_num_threads(), io.StringIO()
    start = time.perf_counter()
    try:
        with contextlib.redirect_stdout(printed):
            status = main(["--out", str(out), "--scale", "tiny", "--no-progress-bar"])
    finally:
        th.set_num_threads(threads)
    print(f"tiny reproduction: {time.perf_counter() - start:.1f} s")
    return out, status, printed.getvalue()
