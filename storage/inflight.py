"""Zarr operations still in flight after the call that started them has returned.

zarr runs every synchronous call as a coroutine on its own event loop thread, and reads
or writes the chunks of one call concurrently (``asyncio.gather`` of one task per chunk).
When one chunk fails (a damaged chunk, a full disk) the call raises at once, but the
other chunks' tasks keep running on that loop: the failed call's siblings outlive it.
Nothing waits for them, so they may still be reading or writing when the task that
started them has been reported failed, when the same chunks are written again, or when
the process ends (then they fail on the interpreter's closed thread pool, "cannot
schedule new futures after shutdown", or on the closed loop, and print tracebacks).
:func:`settle` waits until every operation in flight on zarr's loop at the time of the
call has ended; the task runner calls it when a task fails, and the command line before
the process exits.
"""

from __future__ import annotations

import asyncio
import logging
import threading

__all__ = ["settle"]

log = logging.getLogger(__name__)


def settle(timeout: float = 60.0) -> bool:
    """Wait (at most ``timeout`` seconds) until the operations running on zarr's event loop
    when this is called have ended; True if they have (or there were none).

    Only waits: an operation of another thread in flight meanwhile completes as it would
    have; operations started after the call are not waited for.
    """
    from zarr.core import sync as zsync

    loop = zsync.loop[0]
    if loop is None or loop.is_closed() or not loop.is_running() or threading.current_thread() is zsync.iothread[0]:
        return True

    async def others_done() -> bool:
        me = asyncio.current_task()
        pending = {t for t in asyncio.all_tasks() if t is not me and not t.done()}
        if not pending:
            return True
        _, left = await asyncio.wait(pending, timeout=timeout)
        return not left

    try:
        done = asyncio.run_coroutine_threadsafe(others_done(), loop).result(timeout + 5.0)
    except Exception:  # noqa: BLE001 - the loop stopped meanwhile (interpreter exit): nothing to wait for
        return True
    if not done:
        log.debug("zarr operations still in flight after %.0f s", timeout)
    return bool(done)
