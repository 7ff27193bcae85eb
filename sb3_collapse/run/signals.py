"""Stopping a training run at a signal (:func:`stop_signals`) or a request from any thread
(:func:`request_training_stop`): its checkpoint callback writes a checkpoint, then ``learn()`` stops."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sb3_collapse.run.checkpoints import ResumableCheckpoints

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
_stop_requests: list[str] = []  # signal names of request_training_stop calls not yet cleared
_training: list[ResumableCheckpoints] = []  # the checkpoint callbacks of the runs inside stop_signals


def request_training_stop(signal_name: str) -> None:
    """Ask the training of this process, from any thread, to write a checkpoint and stop as the signal ``signal_name``
    (``"SIGTERM"``) would (a run not started yet: at its start)."""
    _stop_requests.append(signal_name)
    for checkpoints in _training.copy():  # a copy: a run may end in another thread meanwhile
        checkpoints.request_stop(signal_name)


def clear_training_stop() -> None:
    """Forget the requests of :func:`request_training_stop`: a later run of this process trains again."""
    _stop_requests.clear()


class StopSignals:
    """What :func:`stop_signals` yields: ``doing``, what a stop signal does now, in the line it prints (the run sets
    it as it goes from training to its final outputs), and :meth:`abortable` for a long step a checkpoint replaces."""

    def __init__(self, checkpoints: ResumableCheckpoints) -> None:
        self.checkpoints = checkpoints
        self.doing = "writing a checkpoint at the end of this round, then stopping"
        self.abort = False

    @contextlib.contextmanager
    def abortable(self, doing: str) -> Iterator[None]:
        """While inside, a stop signal raises ``KeyboardInterrupt(<its name>)`` at once, as does entering after a stop
        was asked for (a signal or :func:`request_training_stop`); ``doing``: what the run does then, in the signal's
        line."""
        self.doing, self.abort = doing, True
        try:
            if self.checkpoints.stop_signal is not None:
                raise KeyboardInterrupt(self.checkpoints.stop_signal)
            yield
        finally:
            self.abort = False


@contextlib.contextmanager
def stop_signals(checkpoints: ResumableCheckpoints) -> Iterator[StopSignals]:
    """While inside, SIGTERM, SIGINT and :func:`request_training_stop` ask ``checkpoints`` (the run's callback) to write
    a checkpoint and stop (``TrainingInterrupted``); a second SIGINT stops at once (``KeyboardInterrupt``). The
    :class:`StopSignals` yielded says what a signal does after ``learn()``."""
    received: list[str] = []  # signals, not requests: a sweep's request and a Ctrl-C are one stop, not two
    stops = StopSignals(checkpoints)

    def handler(signum: int, _frame: Any) -> None:
        name = signal.Signals(signum).name
        if signum == signal.SIGINT and received:
            raise KeyboardInterrupt
        received.append(name)
        checkpoints.request_stop(name)
        again = " (SIGINT again: stop now)" if signum == signal.SIGINT else ""  # a second SIGTERM changes nothing
        print(f"\n{name}: {stops.doing}{again}.", flush=True)
        if stops.abort:
            raise KeyboardInterrupt(name)

    _training.append(checkpoints)
    if _stop_requests:
        checkpoints.request_stop(_stop_requests[0])
    try:
        with stop_signal_handlers(handler):
            yield stops
    finally:
        _training.remove(checkpoints)


@contextlib.contextmanager
def stop_signal_handlers(handler: Callable[[int, Any], None]) -> Iterator[None]:
    """While inside, ``handler`` (``signal.signal``'s) handles SIGTERM and SIGINT (nothing outside the main thread)."""

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
