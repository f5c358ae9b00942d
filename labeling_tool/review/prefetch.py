"""Background preparation: values made ahead in one thread, so that a key finds them ready."""
from __future__ import annotations

import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor


_DROPPED = object()  # what a delayed job that is no longer wanted returns


class Prefetcher:
    """Values by key, made in one background thread when asked ahead (:meth:`want`) or at once when
    needed (:meth:`get`); the newest ``size`` are kept.

    A job may wait ``delay`` seconds before it starts: it is made only if it is still wanted then
    (or at once when :meth:`get` needs it), so costly work that may never be used (the 3D surface
    of a subject the reviewer passes in under a second) does not compete with the keys.
    """

    def __init__(self, size: int):
        self.size = size
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="label-tool-prefetch")
        self._values: OrderedDict = OrderedDict()
        self._futures: dict = {}
        self._wanted: set = set()   # the keys of the latest want()
        self._needed: set = set()   # keys get() waits for: a delayed job starts at once
        self._lock = threading.Lock()

    def _keep(self, key, value):
        with self._lock:
            self._values[key] = value
            self._values.move_to_end(key)
            while len(self._values) > self.size:
                self._values.popitem(last=False)

    def want(self, jobs) -> None:
        """Make these values in the background, in order: jobs (key, maker) or (key, maker, delay
        in seconds); queued work for other keys is dropped."""
        jobs = [(job[0], job[1], job[2] if len(job) > 2 else 0.0) for job in jobs]
        now = time.monotonic()
        with self._lock:
            self._wanted = {k for k, _, _ in jobs}
            for key in list(self._futures):
                if key not in self._wanted and self._futures[key].cancel():
                    del self._futures[key]
            for key, fn, delay in jobs:
                if key not in self._values and key not in self._futures:
                    self._futures[key] = self._pool.submit(self._run, key, fn, now + delay)

    def _run(self, key, fn, start_at: float):
        while time.monotonic() < start_at:
            with self._lock:
                if key in self._needed:
                    break
                if key not in self._wanted:  # moved on before it was due: not made
                    self._futures.pop(key, None)
                    return _DROPPED
            time.sleep(0.02)
        value = fn()
        self._keep(key, value)
        with self._lock:  # done: the value is kept, the future need not be
            self._futures.pop(key, None)
        return value

    def get(self, key, fn):
        with self._lock:
            if key in self._values:
                self._values.move_to_end(key)
                return self._values[key]
            future = self._futures.pop(key, None)
            if future is not None:
                self._needed.add(key)
        try:
            if future is not None and not future.cancel():
                value = future.result()
                if value is not _DROPPED:
                    return value
        finally:
            with self._lock:
                self._needed.discard(key)
        value = fn()
        self._keep(key, value)
        return value

    def clear(self):
        with self._lock:
            self._wanted = set()
            for f in self._futures.values():
                f.cancel()
            self._futures.clear()
            self._values.clear()

    def close(self):
        self.clear()
        self._pool.shutdown(wait=True, cancel_futures=True)
