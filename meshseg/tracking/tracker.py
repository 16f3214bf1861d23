"""Tracker: one MLflow experiment in one store, and the fold runs in it (DESIGN "Tracking contract")."""

from __future__ import annotations

import json
import logging
import random
import tempfile
import time
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from meshseg.errors import TrackingError
from meshseg.tracking.lease import LEASE_OWNER, Heartbeat, Lease, holder, take_over
from meshseg.tracking.pictures import pictures
from meshseg.tracking.record import FoldRecord, is_fold_run
from meshseg.tracking.store import (
    SQLITE,
    UI_URL,
    WholeCalls,
    all_runs,
    check_server,
    file_lock,
    retry,
    server_gone,
    store_uri,
)

log = logging.getLogger(__name__)

#: claims in a row that may meet other claimants before a claim gives up
CLAIM_ATTEMPTS = 20


class Tracker:
    """One MLflow experiment in one store."""

    def __init__(self, uri: str, experiment: str, artifact_dir: str | None = None):
        from mlflow import MlflowClient

        self.uri = store_uri(uri)
        if self.uri.startswith(("http://", "https://")):
            check_server(self.uri)
        if self.uri.startswith(SQLITE):
            # MLflow creates and migrates a new sqlite schema on first use; two processes doing that at
            # once collide ("duplicate column name"), so the first use happens under a lock beside the file.
            with file_lock(Path(self.uri[len(SQLITE) :] + ".lock")):
                self.client = WholeCalls(MlflowClient(tracking_uri=self.uri))
                self.experiment_id = self._experiment(experiment, artifact_dir)
        else:
            self.client = WholeCalls(MlflowClient(tracking_uri=self.uri))
            self.experiment_id = self._experiment(experiment, artifact_dir)

    def _experiment(self, name: str, artifact_dir: str | None) -> str:
        from mlflow.exceptions import MlflowException

        exp = retry(lambda: self.client.get_experiment_by_name(name), "get experiment")
        if exp is not None:
            return exp.experiment_id
        location = None  # a server decides for itself
        if self.uri.startswith(SQLITE):  # a sqlite store keeps its artifacts beside its database file
            folder = Path(artifact_dir) if artifact_dir else Path(self.uri[len(SQLITE) :]).parent / "artifacts"
            location = folder.expanduser().absolute().as_uri()
        try:
            return self.client.create_experiment(name, artifact_location=location)
        except MlflowException:  # another worker created it first
            return self.client.get_experiment_by_name(name).experiment_id

    def runs(self, filter_string: str = "") -> list:
        """All runs of the experiment matching an MLflow filter string, sweeps' parent runs left out (they are no
        folds: meshseg.tracking.sweeps)."""
        return [r for r in all_runs(self.client, self.experiment_id, filter_string) if is_fold_run(r)]

    def finished(self, config_hash: str):
        """The FINISHED run with this config hash, or None."""
        runs = self.runs(f"tags.config_hash = '{config_hash}' and attributes.status = 'FINISHED'")
        return runs[0] if runs else None

    def finished_by_hash(self) -> dict:
        """Every config hash's FINISHED run, as `finished` finds it (the latest started), in one search."""
        found: dict = {}
        for r in self.runs("attributes.status = 'FINISHED'"):
            h = r.data.tags.get("config_hash")
            if h and (h not in found or r.info.start_time > found[h].info.start_time):
                found[h] = r
        return found

    def claim(
        self, name: str, tags: dict, lease: Lease | None = None, start_time: int | None = None
    ) -> tuple[str | None, object | None]:
        """Create this config's run, RUNNING under a lease, unless the config is taken: returns (run id,
        None), or (None, the holder) when another run of the same `config_hash` is FINISHED or held by a
        live process.

        No lock is needed, so it works on any store: every claimant first creates its run, then looks
        at the others, and keeps the config only if it sees no other live run of it. Of two claimants
        the later to be stored sees the earlier, so two can never both keep it (start times cannot
        order them: a client stamps its start time before its run is stored). Claimants that saw each
        other all step back; if a moment later no live run is left, they try again after a random
        pause. A lease is live while its owner's heartbeat tag is younger than `lease.timeout_s` (and,
        on this host, while its process exists); a dead one is taken over and its run marked KILLED."""
        chash, lease = tags["config_hash"], lease or Lease()
        for attempt in range(CLAIM_ATTEMPTS):
            mine = self._create(name, {**tags, **lease.tags()}, start_time).info.run_id
            try:
                others = [r for r in self._config_runs(chash) if r.info.run_id != mine]
                if holder(others) is None:
                    take_over(self.client, others, mine)
                    return mine, None
            except KeyboardInterrupt:  # Ctrl-C or SIGTERM (meshseg.signals.terminate_interrupts) mid-claim
                self.client.set_terminated(mine, "KILLED")
                raise
            self.client.set_terminated(mine, "KILLED")  # a claim that stepped back is no run in progress
            self.client.delete_run(mine)
            time.sleep(random.uniform(0.05, 0.25) * min(attempt + 1, 4))
            # a holder that is still there is not a fellow claimant stepping back: it keeps the config
            if (kept := holder(self._config_runs(chash))) is not None:
                return None, kept
        raise TrackingError(f"config {chash}: {CLAIM_ATTEMPTS} claims in a row met other claimants; run it again")

    def _config_runs(self, chash: str) -> list:
        return self.runs(f"tags.config_hash = '{chash}'")

    def _create(self, name: str, tags: dict, start_time: int | None = None):
        from mlflow.utils.mlflow_tags import MLFLOW_RUN_NAME

        tags = {**{k: str(v) for k, v in tags.items()}, MLFLOW_RUN_NAME: name}
        return retry(
            lambda: self.client.create_run(self.experiment_id, start_time=start_time, run_name=name, tags=tags),
            "create run",
        )

    @contextmanager
    def run(self, name: str, tags: dict, params: dict, run_id: str | None = None) -> Iterator[str]:
        """Yield a run's id (`run_id`, claimed before, or a new run) and end it FINISHED, FAILED (error
        text tagged) or KILLED. A claimed run's heartbeat is kept fresh meanwhile."""
        run_id = run_id or self._create(name, tags).info.run_id
        beat = None
        try:
            beat = Heartbeat(self.client, run_id) if self._leased(run_id) else None
            self.log_params(run_id, params)
            yield run_id
        except KeyboardInterrupt:
            self._end(beat, run_id, "KILLED")
            raise
        except BaseException as e:
            self._failed(beat, run_id, e)
            if gone := server_gone(f"run {run_id}", e):  # e.g. an artifact upload: one line, not MLflow's page
                raise gone from None
            raise
        else:
            self._end(beat, run_id, "FINISHED")

    @contextmanager
    def files_at_end(self, run_id: str, files) -> Iterator[None]:
        """`files()` (paths, e.g. the job's log) stored with the run however the block ends."""
        try:
            yield
        finally:  # also (especially) for a run that failed
            try:
                self.log_files(run_id, files())
            except Exception as e:  # never hides what ended the run
                log.warning("run %s: its files were not stored: %s", run_id, str(e)[:300])

    @contextmanager
    def system_metrics(self, run_id: str, on: bool) -> Iterator[None]:
        """MLflow's CPU, memory and GPU samples as the run's system metrics while the block runs, when `on`."""
        if not on:
            yield
            return
        import mlflow
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        mlflow.set_tracking_uri(self.uri)  # the monitor logs through the default client
        monitor = SystemMetricsMonitor(run_id, sampling_interval=10, samples_before_logging=1)
        monitor.start()
        try:
            yield
        finally:
            monitor.finish()

    def _failed(self, beat, run_id: str, e: BaseException) -> None:
        """End a run FAILED with its error text tagged and its traceback logged, if the store lets us."""
        text = "".join(traceback.format_exception_only(type(e), e)).strip()
        try:
            self.client.set_tag(run_id, "error", text[:5000])
            self.client.log_text(run_id, traceback.format_exc(), "error.txt")
            self._end(beat, run_id, "FAILED")
        except Exception as why:  # the store itself is gone: the run stays RUNNING until a rerun takes it over
            if beat is not None:
                beat.stop()
            log.warning("run %s could not be marked FAILED: %s", run_id, str(why).splitlines()[0][:300])

    def _leased(self, run_id: str) -> bool:
        return LEASE_OWNER in self.client.get_run(run_id).data.tags

    def _end(self, beat, run_id: str, status: str) -> None:
        if beat is not None:
            beat.stop()
        retry(lambda: self.client.set_terminated(run_id, status), "end run")

    def log_metrics(self, run_id: str, metrics: dict[str, float], model_id: str | None = None) -> None:
        """The run's metrics, also shown as the metrics of its logged model `model_id` when one is given."""
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, 0, model_id=model_id) for k, v in metrics.items()]
        retry(lambda: self.client.log_batch(run_id, metrics=items), "log metrics")

    def log_params(self, run_id: str, params: dict) -> None:
        from mlflow.entities import Param

        items = [Param(k, str(v)[:6000]) for k, v in params.items()]
        for i in range(0, len(items), 100):
            retry(lambda i=i: self.client.log_batch(run_id, params=items[i : i + 100]), "log params")

    def log_fold(
        self, run_id: str, config_yaml: str, rows: list[dict], predictions: dict[str, np.ndarray] | None
    ) -> None:
        """The fold's record as `FoldRecord` names it: the config, the per-mesh table (its columns in
        FoldRecord's order) and the per-face predictions, each array cast to its FoldRecord dtype (None: a
        run imported from a `results/` record without labels; a record's labels come as the `labels_` arrays alone)."""
        R = FoldRecord
        arrays = None if predictions is None else R.prediction_arrays(predictions)  # a bad key: nothing logged
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            (d / R.CONFIG).write_text(config_yaml)
            (d / R.PER_MESH).write_text(R.per_mesh_csv(rows))
            for name in (R.CONFIG, R.PER_MESH):
                self.client.log_artifact(run_id, str(d / name))
        if arrays is not None:
            self.log_predictions(run_id, arrays)

    def log_predictions(self, run_id: str, predictions: dict[str, np.ndarray]) -> None:
        """The per-face arrays as the run's FoldRecord.PREDICTIONS, each cast to its FoldRecord dtype (e.g. the
        labels a `results/` record gained after its run was imported)."""
        arrays = FoldRecord.prediction_arrays(predictions)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / FoldRecord.PREDICTIONS
            np.savez_compressed(path, **arrays)
            self.client.log_artifact(run_id, str(path))

    def log_json(self, run_id: str, name: str, data) -> None:
        """`data` as the run's artifact `name` (JSON)."""
        retry(lambda: self.client.log_dict(run_id, data, name), f"log {name}")

    def log_model(self, run_id: str, save, tags: dict) -> str:
        """An MLflow logged model of the run, named FoldRecord.MODEL (the run's Logged models, `runs:/<run id>/model`):
        created here with `tags`, its files written by `save(model_id)` (meshseg.pyfunc, through MLflow's own
        model logging, which talks to the store by its tracking uri); returns its id."""
        import mlflow
        from mlflow.entities import LoggedModelOutput

        tags, name = {k: str(v) for k, v in tags.items()}, FoldRecord.MODEL
        model = retry(
            lambda: self.client.create_logged_model(self.experiment_id, name=name, source_run_id=run_id, tags=tags),
            "create model",
        )
        mlflow.set_tracking_uri(self.uri)
        save(model.model_id)
        retry(lambda: self.client.log_outputs(run_id, [LoggedModelOutput(model.model_id, 0)]), "link model")
        return model.model_id

    def log_dataset(self, run_id: str, name: str, digest: str, source: str) -> None:
        """The run's data as MLflow's dataset input (the UI's Datasets column): `name` (dataset/category),
        `digest` (the data hash) and `source` (where the data is read from)."""
        from mlflow.entities import Dataset, DatasetInput, InputTag

        data = Dataset(name=name, digest=digest[:36], source_type="local", source=json.dumps({"uri": source}))
        inp = DatasetInput(data, [InputTag("mlflow.data.context", "training")])
        # MLflow's store looks a dataset up, then inserts it: two folds of one category that log it at
        # once race, and the loser gets a unique-key violation. Retried, it finds the winner's row.
        retry(lambda: self.client.log_inputs(run_id, [inp]), "log dataset", transient=("locked", "unique"))

    def log_files(self, run_id: str, paths) -> None:
        """Files as top-level artifacts (the Hydra job's overrides and log); missing ones are skipped."""
        for p in paths:
            if Path(p).is_file():
                retry(lambda p=p: self.client.log_artifact(run_id, str(p)), "log files")

    def log_pictures(self, run_id: str, meshes, labels, rows: list[dict], n: int) -> None:
        """The pictures the MLflow UI shows (`meshseg.tracking.pictures`): renders/mesh_<id>.png for up to
        `n` test meshes and confusion.png."""
        with tempfile.TemporaryDirectory() as tmp:
            for artifact, png in pictures(meshes, labels, rows, n).items():
                path = Path(tmp) / artifact
                path.parent.mkdir(exist_ok=True)
                path.write_bytes(png)
                folder = str(Path(artifact).parent)
                self.client.log_artifact(run_id, str(path), None if folder == "." else folder)

    def _ui(self, ui: str | None) -> str:
        """The MLflow UI's address: the tracking server's own, or `ui` (`make ui`'s, for a sqlite store)."""
        base = self.uri if self.uri.startswith(("http://", "https://")) else (ui or UI_URL)
        return f"{base.rstrip('/')}/#/experiments/{self.experiment_id}/runs"

    def run_url(self, run_id: str, ui: str | None = None) -> str:
        """The run's page in the MLflow UI."""
        return f"{self._ui(ui)}/{run_id}"

    def runs_url(self, ui: str | None = None) -> str:
        """The experiment's runs table (MLflow 3 opens an experiment in its GenAI view otherwise)."""
        return f"{self._ui(ui)}?workflowType=machine_learning"

    def lightning_logger(self, run_id: str):
        """Lightning's MLflow logger writing epoch curves into this run (and leaving it open)."""
        from pytorch_lightning.loggers import MLFlowLogger

        class _FoldLogger(MLFlowLogger):
            def __init__(self, **kwargs):
                super().__init__(**kwargs)
                self._mlflow_client = WholeCalls(self._mlflow_client)  # epoch curves are store writes too

            def finalize(self, status: str = "success") -> None:
                pass  # the run ends after evaluation, in Tracker.run

        return _FoldLogger(tracking_uri=self.uri, run_id=run_id)
