"""Ends a sweep's local Ray instance and its workers when the driver dies, even by SIGKILL (see ``ray_session``)."""

from __future__ import annotations

import contextlib
import os
import sys
import time

import psutil


def _descendants(pid: int) -> dict[tuple[int, float], psutil.Process]:
    """The descendants of ``pid`` but this process, by (pid, creation time): a reused pid is never taken."""
    try:
        children = psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return {}
    found = {}
    for child in children:
        with contextlib.suppress(psutil.NoSuchProcess):
            if child.pid != os.getpid():  # the watchdog is the driver's child too
                found[(child.pid, child.create_time())] = child
    return found


def _end_processes(processes: list[psutil.Process], grace_seconds: float = 5.0) -> None:
    """Terminate the processes, then kill those still alive after ``grace_seconds``."""
    for process in processes:
        with contextlib.suppress(psutil.NoSuchProcess):
            process.terminate()
    for process in psutil.wait_procs(processes, timeout=grace_seconds)[1]:
        with contextlib.suppress(psutil.NoSuchProcess):
            process.kill()


def _driver_alive(process: psutil.Process) -> bool:
    """Whether the driver process still runs (a zombie has died)."""
    try:
        return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def watch(driver_pid: int, poll_seconds: float = 0.5) -> int:
    """Follow the descendants of ``driver_pid`` until it dies, then end those still running; return how many."""
    try:
        driver = psutil.Process(driver_pid)
    except psutil.NoSuchProcess:
        return 0
    known: dict[tuple[int, float], psutil.Process] = {}
    while _driver_alive(driver):
        known.update(_descendants(driver_pid))
        time.sleep(poll_seconds)
    remaining = [process for process in known.values() if process.is_running()]  # checks the creation time too
    _end_processes(remaining)
    return len(remaining)


def main(argv: list[str] | None = None) -> int:
    """:return: 0 once the driver (``argv``: ``DRIVER_PID``) has died and what it left was ended; 2 for bad usage"""
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or not argv[0].isdigit():
        print("usage: python -m sb3_collapse.sweep.watchdog DRIVER_PID", file=sys.stderr)
        return 2
    watch(int(argv[0]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
