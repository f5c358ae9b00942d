"""Connecting to Ray for the commands that can run their tasks on a cluster (``--backend ray``)."""
from __future__ import annotations

import logging
import os
import socket
from contextlib import contextmanager
from typing import Callable, Iterator

from .errors import UserError, optional_import


@contextmanager
def ray_connection(address: str | None):
    """Yield the ``ray`` module connected to the cluster this process is already connected to, else
    the one at ``address`` / RAY_ADDRESS, else a private local instance. Only a connection or
    instance made here is closed here. A local instance started here reports no usage statistics,
    has no dashboard UI and keeps its workers' output and its informational messages off the
    terminal. An address that does not answer, or a failed start, is a UserError in one line."""
    ray = optional_import("ray", "ray", "the ray backend")
    ray_logger = logging.getLogger("ray")
    level = ray_logger.level
    started = not ray.is_initialized()
    if started:
        target = address or os.environ.get("RAY_ADDRESS") or ""
        host, sep, port = target.split("://", 1)[-1].rpartition(":")
        if sep and port.isdigit():  # Ray itself keeps retrying an address that does not answer, for minutes
            try:
                socket.create_connection((host.strip("[]") or "127.0.0.1", int(port)), timeout=10).close()
            except OSError as e:
                raise UserError(f"cannot reach the Ray cluster at {target}: {e.strerror or e}") from None
        set_usage_env = "RAY_USAGE_STATS_ENABLED" not in os.environ
        if set_usage_env:
            os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
        except Exception as e:
            ray.shutdown()  # whatever a failed start left running
            ray_logger.setLevel(level)
            raise UserError(f"cannot start or reach Ray ({target or 'local'}): "
                            f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from e
        finally:
            if set_usage_env:
                os.environ.pop("RAY_USAGE_STATS_ENABLED", None)
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()
            ray_logger.setLevel(level)


def ray_results(ray, pending: dict, describe: Callable[[object], str]) -> Iterator[tuple]:
    """(name, result) of each Ray task in ``pending`` ({object ref: name}) as it finishes. A task's own
    error is raised as the task raised it (chained to Ray's, which carries the remote traceback); any
    other Ray error is a RuntimeError naming ``describe(name)``. After an error, an interrupt or
    the caller's early exit (close the iterator), the tasks still pending are cancelled."""
    pending = dict(pending)
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            name = pending.pop(done[0])
            try:
                result = ray.get(done[0])
            except ray.exceptions.RayTaskError as e:
                cause = getattr(e, "cause", None)
                if isinstance(cause, Exception):
                    raise cause from e
                raise RuntimeError(f"{describe(name)} failed on Ray: {e}") from e
            except ray.exceptions.RayError as e:
                raise RuntimeError(f"{describe(name)} failed on Ray ({type(e).__name__}): {e}") from e
            yield name, result
    finally:
        for ref in pending:
            try:
                ray.cancel(ref)
            except Exception:
                pass  # a task that ended meanwhile
