"""
Stopping a training run at a signal: while a run is inside :func:`stop_signals`, SIGTERM and SIGINT ask its
checkpoint callback (:class:`~sb3_collapse.run.checkpoints.ResumableCheckpoints`) to write a checkpoint and stop,
and :func:`request_training_stop` asks the same from any thread (a sweep's trial, at its driver's request). The
handlers' installation (:func:`stop_signal_handlers`) is shared with the sweep's driver.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sb3_collapse.run.checkpoints import ResumableCheckpoints

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
"""The signals that stop a run (or a sweep) after a checkpoint."""


_stop_requests: list[str] = []
"""Signal names of :func:`request_training_stop` calls not yet cleared (this process's training stops at them)."""
_training: list[ResumableCheckpoints] = []
"""The checkpoint callbacks of the runs training in this process (inside :func:`stop_signals`)."""


def request_training_stop(signal_name: str) -> None:
    """
    Ask the training of this process to write a checkpoint and stop, as a SIGTERM would: at once for a run inside
    :func:`stop_signals`, at its start for a run that has not got there yet. Safe from any thread (a sweep's trial
    calls it when its driver asks the trials to stop).

    :param signal_name: the signal the stop stands for (``"SIGTERM"``), named by :class:`TrainingInterrupted`
    """
    _stop_requests.append(signal_name)
    for checkpoints in _training.copy():  # a copy: a run may end in another thread meanwhile
        checkpoints.request_stop(signal_name)


def clear_training_stop() -> None:
    """Forget the requests of :func:`request_training_stop`: a later run of this process trains again."""
    _stop_requests.clear()


@contextlib.contextmanager
def stop_signals(checkpoints: ResumableCheckpoints) -> Iterator[None]:
    """
    While inside, SIGTERM and SIGINT ask ``checkpoints`` to write a checkpoint and stop (the run ends with
    :class:`TrainingInterrupted`); a second SIGINT stops at once (``KeyboardInterrupt``). Outside the main thread,
    no signal handler is installed. A :func:`request_training_stop` (before or while inside) does what a SIGTERM
    does, in any thread.

    :param checkpoints: the run's checkpoint callback
    """
    _training.append(checkpoints)
    if _stop_requests:
        checkpoints.request_stop(_stop_requests[0])
    try:
        with stop_signal_handlers(_stop_handler(checkpoints)):
            yield
    finally:
        _training.remove(checkpoints)


def _stop_handler(checkpoints: ResumableCheckpoints) -> Callable[[int, Any], None]:
    """The SIGTERM and SIGINT handler of :func:`stop_signals`: a first one asks for a checkpoint, a second SIGINT stops
    at once."""
    received: list[str] = []  # signals, not requests: a sweep's request and a Ctrl-C are one stop, not two

    def handler(signum: int, _frame: Any) -> None:
        name = signal.Signals(signum).name
        if signum == signal.SIGINT and received:
            raise KeyboardInterrupt
        received.append(name)
        checkpoints.request_stop(name)
        print(
            f"\n{name}: writing a checkpoint at the end of this round, then stopping (SIGINT again: stop now).",
            flush=True,
        )

    return handler


@contextlib.contextmanager
def stop_signal_handlers(handler: Callable[[int, Any], None]) -> Iterator[None]:
    """
    While inside, ``handler`` handles SIGTERM and SIGINT (:data:`STOP_SIGNALS`); the previous handlers come back at
    the exit. Outside the main thread, where Python cannot install signal handlers, nothing is installed.

    :param handler: a signal handler (:func:`signal.signal`'s: the signal's number and the interrupted frame)
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    for sig in previous:
        signal.signal(sig, handler)
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
