"""The run folder's lock: one process trains into a run folder at a time (:class:`RunLock`)."""

from __future__ import annotations

import contextlib
import errno
import os
import socket
import time
from pathlib import Path
from typing import Any, Self

from sb3_collapse.errors import InputError
from sb3_collapse.protocol import LOCK_FILE


class RunLock:
    """An exclusive ``flock`` on the ``lock_file`` of ``run_dir`` (which must exist; released if the process dies),
    holding the owner's pid, host and start time; a process that finds it taken gets a message naming the ``folder``
    (``"sweep folder"``) and what to do ``instead``."""

    def __init__(
        self,
        run_dir: str | os.PathLike,
        lock_file: str = LOCK_FILE,
        folder: str = "run folder",
        instead: str = "train into another folder",
    ) -> None:
        self.path = Path(run_dir) / lock_file
        self.folder = folder
        self.instead = instead
        self._file: Any = None

    def __enter__(self) -> Self:
        import fcntl

        while True:
            file = open(self.path, "a+")
            try:
                fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as error:
                file.seek(0)
                owner = file.read().strip() or "another process"
                file.close()
                if error.errno not in (errno.EAGAIN, errno.EACCES):
                    raise
                raise InputError(
                    f"{self.folder} {self.path.parent} is in use by {owner}: wait for it to end (or stop it), or "
                    f"{self.instead}."
                ) from None
            with contextlib.suppress(FileNotFoundError):
                if os.stat(self.path).st_ino == os.fstat(file.fileno()).st_ino:
                    break
            file.close()  # its owner deleted the file we locked: lock the one at the path now
        try:
            file.seek(0)
            file.truncate()
            file.write(f"pid {os.getpid()} on host {socket.gethostname()} since {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
            file.flush()
        except OSError as error:  # a full disk: the message names the lock file
            with contextlib.suppress(OSError):
                file.close()  # its unwritten line is dropped (the file descriptor is closed all the same)
            raise OSError(error.errno, error.strerror, str(self.path)) from None
        self._file = file
        return self

    def __exit__(self, *exc: object) -> None:
        if self._file is not None:
            self._file.close()  # releases the flock; the file stays (train() deletes it, locked, once the run finished)
            self._file = None
