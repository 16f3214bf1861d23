"""The MLflow store: its uri checked and made absolute, its server's health, and every call made to it
robust: sqlite's 'database is locked' retried, a server that stopped answering made one TrackingError,
and an interrupt (SIGTERM, Ctrl-C) held until the store call under way returns."""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from meshseg.errors import TrackingError
from meshseg.tracking.record import is_fold_run

log = logging.getLogger(__name__)

#: where `make ui` serves a sqlite store's UI
UI_URL = "http://127.0.0.1:5000"

#: MLflow's store schemes (a `+driver` suffix is allowed on the database ones)
STORE_SCHEMES = ("sqlite", "postgresql", "mysql", "mssql", "file", "http", "https", "databricks")

SQLITE = "sqlite:///"


def store_uri(uri: str) -> str:
    """A relative sqlite path made absolute (so workers and `mlflow ui` agree), its folder created.
    An unknown scheme is refused here, with what is allowed."""
    from urllib.parse import urlparse

    scheme = urlparse(uri).scheme.split("+")[0]
    if scheme not in ("", *STORE_SCHEMES) or (scheme == "" and "://" in uri):
        raise TrackingError(
            f"tracking.uri={uri}: unknown store scheme {scheme!r}; use sqlite:///PATH/mlflow.db, "
            f"http(s)://HOST:PORT (a tracking server) or one of {list(STORE_SCHEMES)}"
        )
    if uri.startswith(SQLITE):
        path = Path(uri[len(SQLITE) :]).expanduser().absolute()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise TrackingError(f"tracking.uri={uri}: cannot create the store's folder {path.parent} ({e})") from None
        if path.is_dir():
            raise TrackingError(f"tracking.uri={uri}: {path} is a folder; name the database file (…/mlflow.db)")
        return SQLITE + str(path)
    return uri


def check_store_exists(uri: str) -> None:
    """For commands that read a store (predict): a sqlite store that is not there is a mistyped path, not a
    new store to create empty."""
    if uri.startswith(SQLITE) and not Path(uri[len(SQLITE) :]).expanduser().is_file():
        raise TrackingError(f"tracking.uri={uri}: no such store (no file {Path(uri[len(SQLITE) :]).expanduser()})")


def check_server(uri: str, timeout: float = 5.0) -> None:
    """An http(s) store must answer its health check within `timeout` seconds: MLflow's own client
    retries for minutes before it gives up."""
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(uri.rstrip("/") + "/health", timeout=timeout) as r:
            if r.status == 200:
                return
            problem = f"its health check answered HTTP {r.status}"
    except urllib.error.HTTPError as e:
        problem = f"its health check answered HTTP {e.code}"
    except (urllib.error.URLError, OSError) as e:
        problem = f"no MLflow server answers ({getattr(e, 'reason', e)})"
    raise TrackingError(f"tracking.uri={uri}: {problem}; start one with `mlflow server` or use a sqlite:/// store")


@contextmanager
def file_lock(path: Path) -> Iterator[None]:
    """An exclusive lock on `path` (created if missing) for the duration of the block: processes on
    one machine initialising one sqlite store take turns."""
    import fcntl

    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


#: the main thread's store call under way (its depth) and an interrupt that arrived during it
_IN_CALL = {"depth": 0, "pending": None}


def interrupt(reason: str) -> None:
    """Stop the fold, from a signal handler (meshseg.signals.terminate_interrupts): KeyboardInterrupt(reason)
    now or, while a store call is under way on the main thread, the moment it returns. Raised inside the
    call, it can leave the call's sqlite write transaction open in this process, and the run's own end
    (KILLED) then waits on that lock until it fails ('database is locked')."""
    if _IN_CALL["depth"]:
        _IN_CALL["pending"] = reason
    else:
        raise KeyboardInterrupt(reason)


@contextmanager
def whole_call():
    """A block (a store call, or several that must end together) that runs to its end before an interrupt
    (`interrupt`) takes effect: the interrupt is raised as the outermost such block ends."""
    if threading.current_thread() is not threading.main_thread():  # signals interrupt the main thread only
        yield
        return
    _IN_CALL["depth"] += 1
    try:
        yield
    finally:
        _IN_CALL["depth"] -= 1
        if _IN_CALL["depth"] == 0 and _IN_CALL["pending"]:
            reason, _IN_CALL["pending"] = _IN_CALL["pending"], None
            raise KeyboardInterrupt(reason)


class WholeCalls:
    """An MlflowClient whose every call runs to its end before an interrupt (`interrupt`) takes effect."""

    def __init__(self, client):
        self._client = client

    def __getattr__(self, name: str):
        attr = getattr(self._client, name)
        if not callable(attr):
            return attr

        def call(*args, **kwargs):
            with whole_call():
                return attr(*args, **kwargs)

        return call


def retry(fn, what: str, attempts: int = 8, transient: tuple[str, ...] = ("locked",)):
    """sqlite under several writer processes can report 'database is locked': back off and retry (any
    error whose text holds one of `transient`, case-blind). A tracking server that stays unreachable
    through MLflow's own HTTP retries is one TrackingError."""
    from mlflow.exceptions import MlflowException

    for i in range(attempts):
        try:
            return fn()
        except MlflowException as e:
            if gone := server_gone(what, e):
                raise gone from None
            if not any(t in str(e).lower() for t in transient) or i == attempts - 1:
                raise
            log.warning("%s: store busy or a concurrent write won, retrying", what)
            time.sleep(0.2 * 2**i)


def server_gone(what: str, e: Exception) -> TrackingError | None:
    """The one-line error for an MLflow HTTP call that failed for want of a server (MLflow's own retries
    spent), or None when `e` is something else."""
    text = str(e)
    if "failed with exception" not in text or "Max retries exceeded" not in text:
        return None
    reasons = ("Connection refused", "timed out", "Connection reset", "Name or service not known")
    why = next((r for r in reasons if r in text), "no connection")
    return TrackingError(f"{what}: the tracking server stopped answering ({why}); a rerun redoes this fold")


def all_runs(client, experiment_id: str, filter_string: str = "") -> list:
    """Every run of the experiment matching an MLflow filter string: all pages, each read with `retry`."""
    out, token = [], None
    while True:
        page = retry(
            lambda token=token: client.search_runs([experiment_id], filter_string, max_results=1000, page_token=token),
            "search runs",
        )
        out.extend(page)
        token = page.token
        if not token:
            return out


def search_runs(uri: str, experiment: str, filter_string: str = "") -> list:
    """Every run of the experiment `experiment` in the store at `uri` that matches `filter_string`, sweeps' parent
    runs left out, read only: [] when the experiment does not exist (it is never created)."""
    from mlflow import MlflowClient

    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # one bar per run otherwise
    client = MlflowClient(tracking_uri=store_uri(uri))
    exp = retry(lambda: client.get_experiment_by_name(experiment), "get experiment")
    return [] if exp is None else [r for r in all_runs(client, exp.experiment_id, filter_string) if is_fold_run(r)]
