"""`mlflow ui` on 127.0.0.1 against the smoke store: the runs and their PNG artifacts are served over
the REST API (what the browser UI shows), and the process tree started here is stopped."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import pytest

from meshseg.tracking import FoldRecord


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get(base: str, endpoint: str, **params):
    url = f"{base}{endpoint}" + (f"?{urllib.parse.urlencode(params)}" if params else "")
    with urllib.request.urlopen(url, timeout=10) as r:
        body = r.read()
    return json.loads(body) if r.headers.get_content_type() == "application/json" else body


def post(base: str, path: str, payload: dict) -> dict:
    req = urllib.request.Request(f"{base}{path}", json.dumps(payload).encode(), {"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read())


def group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


@contextmanager
def mlflow_ui(store: Path):
    """`mlflow ui` on a free port of 127.0.0.1, in its own process group; stopped (group and all) on exit."""
    port = free_port()
    mlflow = Path(sys.executable).with_name("mlflow")
    proc = subprocess.Popen(
        [
            str(mlflow),
            "ui",
            "--backend-store-uri",
            f"sqlite:///{store}/mlflow.db",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.time() + 120
        while True:
            try:
                if get(base, "/health") == b"OK":
                    break
            except OSError:
                pass
            if proc.poll() is not None or time.time() > deadline:
                why = proc.stderr.read().decode()[-2000:] if proc.poll() is not None else "timeout"
                pytest.fail(f"mlflow ui did not come up: {why}")
            time.sleep(0.5)
        yield base, proc, port
    finally:
        os.killpg(proc.pid, signal.SIGTERM)  # the server and its uvicorn workers
        deadline = time.time() + 30
        while (proc.poll() is None or group_alive(proc.pid)) and time.time() < deadline:
            time.sleep(0.2)  # the workers exit a moment after the parent
        if group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_mlflow_ui_serves_the_runs_and_their_pictures_then_stops(smoke_store):
    with mlflow_ui(smoke_store) as (base, proc, port):
        exp = get(base, "/api/2.0/mlflow/experiments/get-by-name", experiment_name="meshseg")["experiment"]
        search = {"experiment_ids": [exp["experiment_id"]], "max_results": 100}
        runs = post(base, "/api/2.0/mlflow/runs/search", search)["runs"]
        finished = [r for r in runs if r["info"]["status"] == "FINISHED"]
        assert len(finished) == 18
        for run in finished[:3]:
            rid = run["info"]["run_id"]
            top = {f["path"] for f in get(base, "/api/2.0/mlflow/artifacts/list", run_id=rid)["files"]}
            assert {"confusion.png", FoldRecord.PER_MESH, FoldRecord.PREDICTIONS, FoldRecord.CONFIG, "renders"} <= top
            listed = get(base, "/api/2.0/mlflow/artifacts/list", run_id=rid, path="renders")["files"]
            renders = [f["path"] for f in listed]
            assert renders and all(p.startswith("renders/mesh_") and p.endswith(".png") for p in renders)
            assert get(base, "/get-artifact", path=renders[0], run_uuid=rid)[:8] == b"\x89PNG\r\n\x1a\n"
        tags = {t["key"]: t["value"] for t in finished[0]["data"]["tags"]}
        assert set(FoldRecord.TAGS) <= set(tags)
    assert proc.returncode is not None and not group_alive(proc.pid)
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=2).close()
