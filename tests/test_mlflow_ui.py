"""`mlflow ui` on 127.0.0.1 against the smoke store: the runs, their PNG artifacts, the sweeps' parent runs and
the folds' logged models are served over the REST API (what the browser UI shows), and the process tree started
here is stopped; in headless Chromium (`make ui-test`), the UI shows them."""

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

from meshseg.sweep import PARENT_RUN_ID
from meshseg.tracking import SWEEP_KEY, FoldRecord


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
        tags = [{t["key"]: t["value"] for t in r["data"]["tags"]} for r in runs]
        parents = {r["info"]["run_id"] for r, t in zip(runs, tags) if SWEEP_KEY in t}
        finished = [r for r, t in zip(runs, tags) if r["info"]["status"] == "FINISHED" and SWEEP_KEY not in t]
        assert len(finished) == 18 and len(parents) == 2  # conftest's two sweeps, each a parent of its folds
        assert {t[PARENT_RUN_ID] for t in tags if SWEEP_KEY not in t} == parents
        models = post(base, "/api/2.0/mlflow/logged-models/search", {"experiment_ids": [exp["experiment_id"]]})
        sources = sorted(m["info"]["source_run_id"] for m in models["models"])  # one logged model per fold
        assert sources == sorted(r["info"]["run_id"] for r in finished)
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


# --- the UI itself, in headless Chromium (make ui-test installs Debian's chromium and chromium-driver) ---------

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
#: flags for Chromium on a machine without a network (else it keeps trying to reach Google's hosts)
CHROMIUM_FLAGS = (
    "--headless --no-sandbox --disable-gpu --disable-quic --no-first-run --disable-background-networking "
    "--disable-component-update --disable-sync --window-size=1600,4000"
).split()


@pytest.fixture
def browser(tmp_path):
    if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
        pytest.skip("no headless browser: `make ui-test` installs Debian's chromium and chromium-driver")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium missing: `make install` installs it")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in [*CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'chromium'}"]:
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    driver.implicitly_wait(0)
    yield driver
    driver.quit()


def wait_for(driver, predicate, what: str, timeout: float = 60):
    """Poll the page until `predicate(body text)` holds (the UI renders after its API calls return)."""
    from selenium.webdriver.common.by import By

    deadline, text = time.time() + timeout, ""
    while time.time() < deadline:
        try:
            text = driver.find_element(By.TAG_NAME, "body").text
            if predicate(text):
                return text
        except Exception:  # the page is being replaced
            pass
        time.sleep(0.5)
    pytest.fail(f"the UI never showed {what}; it showed:\n{text[:3000]}")


def expand(browser, name: str) -> None:
    """Click the toggle of the runs table's row named `name` (a parent run's: its nested runs open under it)."""
    from selenium.webdriver.common.by import By

    (row,) = [r for r in browser.find_elements(By.CSS_SELECTOR, ".ag-row") if name in r.text]
    row.find_element(By.CSS_SELECTOR, "button").click()


@pytest.mark.browser
def test_the_ui_shows_sweeps_their_nested_folds_a_folds_page_and_its_model(smoke_store, browser):
    import getpass

    from selenium.webdriver.common.by import By

    from meshseg.tracking import Tracker

    with mlflow_ui(smoke_store) as (base, _, _):
        tracker = Tracker(f"sqlite:///{smoke_store}/mlflow.db", "meshseg")
        runs = tracker.runs("attributes.status = 'FINISHED'")  # the folds
        names = {r.info.run_name for r in runs}
        assert len(names) == len(runs) == 18  # one distinct name per fold run
        parents = {p.info.run_id: p.info.run_name for p in tracker.client.search_runs([tracker.experiment_id])}
        parents = {i: n for i, n in parents.items() if i in {r.data.tags[PARENT_RUN_ID] for r in runs}}
        assert len(parents) == 2
        # the URL `make ui` prints lands on the runs table: a row per sweep, its folds folded under it
        browser.get(tracker.runs_url(base))
        text = wait_for(browser, lambda t: all(n in t for n in parents.values()), "each sweep's row")
        assert "20 matching runs" in text and not any(n in text for n in names)
        (first, second) = parents
        folds = {r.info.run_name for r in runs if r.data.tags[PARENT_RUN_ID] == first}
        expand(browser, parents[first])
        text = wait_for(browser, lambda t: all(n in t for n in folds), "the folds of the first sweep, once opened")
        assert not any(n in text for n in names - folds)  # the other sweep's folds are still folded under it
        expand(browser, parents[second])
        wait_for(browser, lambda t: all(n in t for n in names), "every fold, under its sweep")
        run = next(r for r in runs if r.data.tags["model"] == "cnn1d")
        tags = run.data.tags
        # a fold's page: its sweep, source, user, git commit, the command line as description, the dataset, its model
        browser.get(tracker.run_url(run.info.run_id, base))
        text = wait_for(browser, lambda t: "About this run" in t and "Logged models (1)" in t, "the run overview")
        dataset = f"{tags['dataset']}/{tags['category']}"
        for shown in ("meshseg.run", getpass.getuser(), tags["git_sha"][:7], "python -m meshseg.run", dataset):
            assert shown in text, shown
        assert f"Parent run\n{parents[tags[PARENT_RUN_ID]]}" in text
        # the fold's model: listed on the experiment's Models tab by its run, its page with the fold's test/acc
        (output,) = run.outputs.model_outputs
        browser.get(f"{base}/#/experiments/{tracker.experiment_id}/models?workflowType=machine_learning")
        text = wait_for(browser, lambda t: all(n in t for n in names), "every fold's model, by its run")
        browser.get(f"{base}/#/experiments/{tracker.experiment_id}/models/{output.model_id}")
        text = wait_for(browser, lambda t: "Metrics (" in t and run.info.run_name in t, "the model's page")
        assert f"{FoldRecord.ACC}\n-\n{run.info.run_name}\n{run.data.metrics[FoldRecord.ACC]}" in text
        # the train/loss curve, one point per epoch
        browser.get(tracker.run_url(run.info.run_id, base) + "/model-metrics")
        wait_for(browser, lambda t: "\ntrain\n(" in t, "the metric charts")
        box = browser.find_element(By.CSS_SELECTOR, "input[placeholder='Search metric charts']")
        box.send_keys("train/loss")
        # the search leaves one section, `train`, with one chart, `loss` (MLflow groups metrics by prefix)
        wait_for(browser, lambda t: "\ntrain\n(1)" in t and "\nloss\n" in t, "the train/loss chart")
        # a render of a test mesh, predicted beside ground truth, shown as an image
        render = next(f.path for f in tracker.client.list_artifacts(run.info.run_id, "renders"))
        browser.get(tracker.run_url(run.info.run_id, base) + f"/artifacts/{render}")
        deadline = time.time() + 60
        while time.time() < deadline:
            widths = [
                browser.execute_script("return arguments[0].naturalWidth", i)
                for i in browser.find_elements(By.TAG_NAME, "img")
            ]
            if any(w and w > 300 for w in widths):
                break
            time.sleep(0.5)
        else:
            pytest.fail(f"no render shown for {render}: image widths {widths}")
