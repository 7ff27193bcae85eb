"""The Ray cluster of a sweep: Ray's import, the check that a cluster answers, the session and its resources."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Mapping
from typing import Any

from sb3_collapse.errors import ClusterUnreachable, InputError, MissingDependencyError

CONNECT_TIMEOUT_S = 30.0  # seconds a sweep waits for the Ray cluster at its address to answer


def import_ray() -> Any:
    """The ``ray`` module; ``MissingDependencyError`` with the command that installs it."""
    try:
        import ray
    except ImportError as error:
        raise MissingDependencyError(
            f"Sweeps run on Ray, which is not installed: pip install -e '.[sweep]' ({error})."
        ) from None
    return ray


def _wait_for_port(address: str, timeout_s: float) -> None:
    """Wait until something accepts TCP connections at ``address`` (``host:port`` or ``ray://host:port``)."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise InputError(f"address {address!r} is not 'auto', 'host:port' or 'ray://host:port'.", parameter="address")
    host, port = host.strip("[]"), int(port)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=max(0.1, min(5.0, deadline - time.monotonic()))):
                return
        except socket.gaierror as error:
            raise InputError(f"address {address}: no host {host!r} ({error.strerror}).", parameter="address") from None
        except OSError as error:
            reason = error.strerror or type(error).__name__
        if time.monotonic() + 0.5 >= deadline:
            raise ClusterUnreachable(
                f"address {address}: no Ray cluster answered within {timeout_s:g} s ({reason}). Start it (ray start "
                "--head, docs/sweeps.md) or correct the address, then run the same command again; nothing was written."
            )
        time.sleep(0.5)


def check_cluster(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """
    Check that the Ray cluster at ``address`` (``"auto"``, ``"host:port"``, ``"ray://host:port"``: reachability only)
    accepts this process within ``timeout_s`` seconds (``ray.init`` alone retries for minutes), Ray's log lines muted.
    """
    deadline = time.monotonic() + timeout_s
    if address == "auto":
        try:  # Ray's own resolution of "auto" (private: another Ray version may lack it, then ray.init resolves it)
            from ray._private.authentication.authentication_token_setup import (
                maybe_enable_token_auth_if_token_available,
            )
            from ray._private.services import canonicalize_bootstrap_address_or_die
        except ImportError:
            return
        maybe_enable_token_auth_if_token_available(warn_if_disabled=False)  # as ray.init does for "auto"
        try:
            address = canonicalize_bootstrap_address_or_die("auto")
        except ConnectionError as error:
            raise ClusterUnreachable(
                f"address auto: {error} Start a cluster on this machine (ray start --head) or give its address, then "
                "run the same command again; nothing was written."
            ) from None
    _wait_for_port(address, timeout_s)
    try:
        from ray._raylet import GcsClient
    except ImportError:  # another Ray version: reachability is all that is checked
        return
    if address.startswith("ray://"):
        return
    outcome: list[BaseException | None] = []

    def connect() -> None:
        try:
            GcsClient(address=address)
            outcome.append(None)
        except Exception as error:  # noqa: BLE001  reported below
            outcome.append(error)

    with _stderr_captured():
        thread = threading.Thread(target=connect, daemon=True)
        thread.start()
        thread.join(max(1.0, deadline - time.monotonic()))
    if not outcome:
        raise ClusterUnreachable(
            f"address {address}: a process listens there, but no Ray cluster answered within {timeout_s:g} s. Check "
            "the address (the head's GCS port, 6379 by default) and the cluster, then run the same command again; "
            "nothing was written."
        )
    error = outcome[0]
    if error is None:
        return
    if type(error).__name__ == "AuthenticationError":
        token_mode = os.environ.get("RAY_AUTH_MODE", "").lower() == "token"
        raise InputError(
            f"address {address}: the Ray cluster there wants an authentication token and "
            + (
                "the token of this process (RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token) is not its own"
                if token_mode
                else "this process sends none (ray start turns token authentication on by default)"
            )
            + ": set RAY_AUTH_MODE=token and the cluster's token (RAY_AUTH_TOKEN=<token>, or the file "
            "~/.ray/auth_token; `ray get-auth-token` on the head prints it), or start the cluster with "
            "RAY_AUTH_MODE=disabled (docs/sweeps.md). Nothing was written.",
            parameter="address",
        )
    first_line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    raise ClusterUnreachable(
        f"address {address}: no Ray cluster answered there ({first_line}). Check the address (the head's GCS port, "
        "6379 by default) and the cluster, then run the same command again; nothing was written."
    )


@contextlib.contextmanager
def _stderr_captured() -> Iterator[None]:
    """Send what is written to file descriptor 2 (Ray's C++ log lines) nowhere while inside."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


@contextlib.contextmanager
def ray_session(
    address: str | None = None, num_cpus: int | None = None, connect_timeout_s: float = CONNECT_TIMEOUT_S
) -> Iterator[Any]:
    """
    Ray for the block: an initialized Ray as it is, else a new local instance (ended with this process, even by
    SIGKILL) or the cluster at ``address``, checked first (:func:`check_cluster`).

    :param address: Ray cluster address, ``None`` for a new local instance (also where a ``ray start`` cluster runs
        on this machine or ``RAY_ADDRESS`` is set: Ray's own ``None`` would join those)
    :param num_cpus: CPUs of a new local instance (``None``: all of the machine's); ignored with ``address``
    :param connect_timeout_s: seconds to wait for the cluster at ``address`` to answer
    :return: the ``ray`` module
    :raises ClusterUnreachable: when the cluster at ``address`` did not answer in time
    :raises InputError: for a wrong address, or a cluster that wants a token this process lacks
    """
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    watchdog = None
    if address is None:
        ray.init(address="local", include_dashboard=False, num_cpus=num_cpus, log_to_driver=True)
        watchdog = subprocess.Popen(  # not in the driver's process group: a Ctrl-C or a group kill does not reach it
            [sys.executable, "-m", "sb3_collapse.sweep.watchdog", str(os.getpid())], stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
        )  # fmt: skip
    else:
        check_cluster(address, connect_timeout_s)
        try:
            ray.init(address=address, log_to_driver=True)
        except ConnectionError as error:
            raise ClusterUnreachable(
                f"address {address}: {error}. Check the cluster, then run the same command again; nothing was written."
            ) from None
    try:
        yield ray
    finally:
        ray.shutdown()
        if watchdog is not None:
            watchdog.terminate()
            watchdog.wait()


def check_resources(resources: Mapping[str, float], cpus_per_trial: float, gpus_per_trial: float) -> None:
    """An ``InputError`` when no trial could ever be scheduled on the cluster's ``resources``."""
    gpus, cpus = resources.get("GPU", 0.0), resources.get("CPU", 0.0)
    if gpus_per_trial > 0 and gpus == 0:
        raise InputError(
            f"gpus_per_trial={gpus_per_trial} asks for GPUs, but Ray sees none in this cluster (resources: "
            f"{dict(resources)}). Set gpus_per_trial=0 to train on CPU, or run on machines with GPUs.",
            parameter="gpus_per_trial",
        )
    for name, unit, asked, seen in (
        ("gpus_per_trial", "GPUs", gpus_per_trial, gpus),
        ("cpus_per_trial", "CPUs", cpus_per_trial, cpus),
    ):
        if asked > seen:
            raise InputError(f"{name}={asked} is more than the {seen:g} {unit} Ray sees.", parameter=name)
