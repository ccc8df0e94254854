"""One writer per result store: a lease file beside the store.

A run (and ``schlieren verify --repair``) holds ``<store>.lease`` (next to the store
folder, not inside it: zarr and xarray warn about non-Zarr files in the hierarchy) while
it writes. The store's path is resolved first (symbolic links followed): two paths to one
store share its lease. The file records the holder's host, pid, process start time and a random
token; the holder touches it every ``heartbeat`` seconds from a daemon thread. Another
writer is refused with one line naming the holder, unless the lease is *stale*:

* the holder ran on this host and its process is gone (or its pid now belongs to a
  process started at another time): a run killed with ``kill -9`` is resumed at once;
* or the lease has not been touched for ``timeout`` seconds (a holder on another host
  that died).

The lease is taken atomically (``link`` of a complete file, which fails if one exists)
and a stale one is moved aside before the new one is linked, so two writers racing for
a stale lease cannot both win.

Stores on S3 (``s3://``, and S3-compatible servers that implement conditional writes)
get the same lease as an object ``<store>.lease`` (:class:`ObjectStoreLease`): taken with
a conditional PUT (``If-None-Match: *``), kept alive and taken over with conditional
PUTs on the ETag the writer last saw (``If-Match``: of several writers racing for a
stale lease exactly one replaces it), released with a conditional DELETE. Its age is the
object's ``LastModified`` against this host's clock (keep clocks within a few seconds of
the server's; the timeout is a minute). Other object stores (``gs://``, ``az://``) have
no lease: a warning says so.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
import uuid
from pathlib import Path

from schlieren.storage.errors import StoreError

__all__ = ["StoreLease", "ObjectStoreLease", "LeaseError", "lease_path", "lease_for", "HEARTBEAT_SECONDS",
           "STALE_SECONDS"]

log = logging.getLogger(__name__)

HEARTBEAT_SECONDS = 10.0
STALE_SECONDS = 60.0


class LeaseError(StoreError):
    """Another live run holds the store's lease."""


def lease_path(store_path: str | os.PathLike) -> Path:
    """``<store>.lease`` beside the store, its path resolved (symbolic links followed), so
    that every path to one store names one lease."""
    p = Path(os.path.realpath(os.fspath(store_path)))
    return p.with_name(p.name + ".lease")


def _process_start(pid: int) -> float | None:
    try:
        import psutil

        return float(psutil.Process(pid).create_time())
    except Exception:  # noqa: BLE001 - gone, or no permission
        return None


def _alive(info: dict) -> bool:
    """Is the holder recorded in ``info`` (on this host) still running?"""
    try:
        pid = int(info["pid"])
    except (KeyError, TypeError, ValueError):
        return False
    started = _process_start(pid)
    if started is None:
        return False
    want = info.get("process_start")
    return want is None or abs(float(want) - started) < 1.0


class StoreLease:
    """The lease of one store; use as a context manager or call :meth:`acquire`/:meth:`release`."""

    def __init__(self, store_path: str | os.PathLike, *, purpose: str = "run",
                 heartbeat: float = HEARTBEAT_SECONDS, timeout: float = STALE_SECONDS):
        self.path = lease_path(store_path)
        self.store = os.fspath(store_path)
        self._setup(purpose, heartbeat, timeout)

    def _setup(self, purpose: str, heartbeat: float, timeout: float) -> None:
        self.purpose = purpose
        self.heartbeat = float(heartbeat)
        self.timeout = float(timeout)
        self.token = uuid.uuid4().hex
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.held = False

    # -- reading -------------------------------------------------------------------
    def holder(self) -> tuple[dict, float] | None:
        """``(recorded info, seconds since the last heartbeat)`` of the current lease, or None."""
        try:
            age = max(time.time() - self.path.stat().st_mtime, 0.0)
            info = json.loads(self.path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return {}, age  # unreadable: held until it is older than the timeout
        return (info if isinstance(info, dict) else {}), age

    def _stale(self, info: dict, age: float) -> str | None:
        if info.get("host") == socket.gethostname() and info.get("pid") is not None:
            if not _alive(info):
                return f"its process {info.get('pid')} on this host is gone"
            return None
        if age > self.timeout:
            return f"no heartbeat for {age:.0f} s"
        return None

    # -- taking and giving back -------------------------------------------------------
    def acquire(self) -> "StoreLease":
        """Take the lease, or raise :class:`LeaseError` naming the live holder."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        info = {"host": socket.gethostname(), "pid": os.getpid(), "process_start": _process_start(os.getpid()),
                "token": self.token, "purpose": self.purpose, "store": self.store,
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        tmp = self.path.with_name(f".{self.path.name}.{self.token}.tmp")
        try:
            tmp.write_text(json.dumps(info))
        except OSError as exc:
            raise StoreError(f"cannot write the store's lease file ({exc.strerror or exc})",
                             file=str(self.path)) from None
        try:
            for _ in range(20):
                try:
                    os.link(tmp, self.path)
                    self.held = True
                    break
                except FileExistsError:
                    pass
                got = self.holder()
                if got is None:
                    continue  # released meanwhile: try again
                other, age = got
                why = self._stale(other, age)
                if why is None:
                    raise LeaseError(
                        f"another {other.get('purpose', 'run')} is writing this store (host "
                        f"{other.get('host', '?')}, pid {other.get('pid', '?')}, since {other.get('started', '?')}, "
                        f"heartbeat {age:.0f} s ago); wait for it to finish, or stop it (a lease without "
                        f"heartbeat for {self.timeout:.0f} s is taken over)", file=self.store, field="lease")
                log.warning("taking over the lease of %s: %s", self.store, why)
                aside = self.path.with_name(f".{self.path.name}.{uuid.uuid4().hex}.stale")
                try:
                    os.rename(self.path, aside)  # only one of several takers moves it
                    os.remove(aside)
                except FileNotFoundError:
                    pass
            else:  # pragma: no cover - twenty lost races in a row
                raise LeaseError("could not take the store's lease (contended)", file=self.store, field="lease")
        finally:
            try:
                tmp.unlink()
            except FileNotFoundError:
                pass
        self._thread = threading.Thread(target=self._beat, name="schlieren-lease", daemon=True)
        self._thread.start()
        return self

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat):
            try:
                info = json.loads(self.path.read_text())
                if info.get("token") != self.token:
                    log.error("the lease of %s was taken over by %s (pid %s)", self.store, info.get("host"),
                              info.get("pid"))
                    return
                os.utime(self.path)
            except (OSError, ValueError) as exc:
                log.warning("lease heartbeat of %s failed: %s", self.store, exc)

    def _give_up(self) -> bool:
        """Stop the heartbeat; True if the lease was held (and is to be removed now)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        held, self.held = self.held, False
        return held

    def release(self) -> None:
        if not self._give_up():
            return
        try:
            info = json.loads(self.path.read_text())
            if info.get("token") == self.token:
                self.path.unlink()
        except (OSError, ValueError):
            pass

    def __enter__(self) -> "StoreLease":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _holder_message(store: str, other: dict, age: float, timeout: float) -> LeaseError:
    return LeaseError(
        f"another {other.get('purpose', 'run')} is writing this store (host {other.get('host', '?')}, pid "
        f"{other.get('pid', '?')}, since {other.get('started', '?')}, heartbeat {age:.0f} s ago); wait for it "
        f"to finish, or stop it (a lease without heartbeat for {timeout:.0f} s is taken over)",
        file=store, field="lease")


def _precondition_failed(exc: BaseException) -> bool:
    """A conditional S3 request refused (HTTP 412), as botocore or s3fs report it."""
    resp = getattr(exc, "response", None) or getattr(getattr(exc, "__cause__", None), "response", None)
    if isinstance(resp, dict):
        err = resp.get("Error", {})
        if err.get("Code") in ("PreconditionFailed", "412") or \
                resp.get("ResponseMetadata", {}).get("HTTPStatusCode") == 412:
            return True
    return isinstance(exc, FileExistsError) or "PreconditionFailed" in str(exc) or "412" in str(exc)


class ObjectStoreLease(StoreLease):
    """The lease of a store on S3: the object ``<store URL>.lease``, written with conditional
    requests (see the module docstring). Same interface as :class:`StoreLease`."""

    def __init__(self, store_url: str, *, purpose: str = "run", heartbeat: float = HEARTBEAT_SECONDS,
                 timeout: float = STALE_SECONDS):
        from schlieren.storage import location

        self._setup(purpose, heartbeat, timeout)
        self.store = location.normalize(store_url).rstrip("/")
        self.url = self.store + ".lease"
        self.path = self.url  # what messages and callers show
        self.fs, self._key = location.filesystem(self.url)
        self._bucket, self._object = self._key.split("/", 1)
        self._etag: str | None = None

    # -- the object ----------------------------------------------------------------------
    def _head(self) -> tuple[bytes, str, float] | None:
        """``(body, ETag, age in seconds)`` of the lease object in one request, or None."""
        try:
            r = self.fs.call_s3("get_object", Bucket=self._bucket, Key=self._object)
        except FileNotFoundError:
            return None
        body = r["Body"]
        data = body if isinstance(body, bytes) else self._read_body(body)
        modified = r.get("LastModified")
        age = max(time.time() - modified.timestamp(), 0.0) if modified is not None else 0.0
        return data, r["ETag"], age

    def _read_body(self, body) -> bytes:
        from fsspec.asyn import sync

        async def read():
            try:
                return await body.read()
            finally:
                body.close()
        return sync(self.fs.loop, read)

    def _put(self, info: dict, **cond) -> str:
        r = self.fs.call_s3("put_object", Bucket=self._bucket, Key=self._object,
                            Body=json.dumps(info).encode(), **cond)
        self.fs.invalidate_cache(self._key)
        return r["ETag"]

    def holder(self) -> tuple[dict, float] | None:
        got = self._head()
        if got is None:
            return None
        data, _, age = got
        try:
            info = json.loads(data)
        except ValueError:
            return {}, age
        return (info if isinstance(info, dict) else {}), age

    # -- taking and giving back -------------------------------------------------------
    def acquire(self) -> "ObjectStoreLease":
        info = {"host": socket.gethostname(), "pid": os.getpid(), "process_start": _process_start(os.getpid()),
                "token": self.token, "purpose": self.purpose, "store": self.store,
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "beat": time.time()}
        for _ in range(20):
            try:
                self._etag = self._put(info, IfNoneMatch="*")
                self.held = True
                break
            except Exception as exc:  # noqa: BLE001 - only a refused condition is expected
                if not _precondition_failed(exc):
                    raise StoreError(f"cannot write the store's lease object ({exc})", file=self.url) from None
            got = self._head()
            if got is None:
                continue  # released meanwhile: try again
            data, etag, age = got
            try:
                other = json.loads(data)
                other = other if isinstance(other, dict) else {}
            except ValueError:
                other = {}
            why = self._stale(other, age)
            if why is None:
                raise _holder_message(self.store, other, age, self.timeout)
            log.warning("taking over the lease of %s: %s", self.store, why)
            try:  # replace exactly the stale lease seen: of several takers one wins
                self._etag = self._put(info, IfMatch=etag)
                self.held = True
                break
            except Exception as exc:  # noqa: BLE001
                if not _precondition_failed(exc):
                    raise StoreError(f"cannot write the store's lease object ({exc})", file=self.url) from None
        else:  # pragma: no cover - twenty lost races in a row
            raise LeaseError("could not take the store's lease (contended)", file=self.store, field="lease")
        self._info = info
        self._thread = threading.Thread(target=self._beat, name="schlieren-lease", daemon=True)
        self._thread.start()
        return self

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat):
            try:  # a new body (ETag = its MD5) each time: the heartbeat is visible, and conditional
                self._info["beat"] = time.time()
                self._etag = self._put(self._info, IfMatch=self._etag)
            except Exception as exc:  # noqa: BLE001
                if _precondition_failed(exc):
                    got = self.holder()
                    other = got[0] if got else {}
                    log.error("the lease of %s was taken over by %s (pid %s)", self.store, other.get("host"),
                              other.get("pid"))
                    return
                log.warning("lease heartbeat of %s failed: %s", self.store, exc)

    def release(self) -> None:
        if not self._give_up():
            return
        try:  # only our own lease: a conditional DELETE on the ETag we last wrote
            self.fs.call_s3("delete_object", Bucket=self._bucket, Key=self._object, IfMatch=self._etag)
        except Exception as exc:  # noqa: BLE001 - taken over meanwhile (412), or already gone
            if not _precondition_failed(exc) and not isinstance(exc, FileNotFoundError):
                log.warning("could not release the lease of %s: %s", self.store, exc)
        self.fs.invalidate_cache(self._key)


def lease_for(store, purpose: str = "run"):
    """The lease of ``store``: a folder's lease file, an S3 store's lease object; a no-op
    context (with a warning) for other object stores and for store objects."""
    import contextlib

    from schlieren.storage import location

    if isinstance(store, (str, os.PathLike)):
        loc = os.fspath(store)
        if not location.is_url(loc):
            return StoreLease(loc, purpose=purpose)
        if loc.startswith(("s3://", "s3a://")):
            return ObjectStoreLease(loc, purpose=purpose)
        log.warning("%s: no one-writer lease on %s:// stores (only folders and s3://); do not run two "
                    "writers on it at once", location.display(loc), loc.split("://", 1)[0])
    return contextlib.nullcontext()
