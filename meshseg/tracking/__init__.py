"""MLflow under the tracking contract (DESIGN "Tracking contract"): one run per (method config,
dataset, category, split, fold), tagged with every knob the report needs; params are the flattened
resolved config; artifacts are the config, a per-mesh table, the per-face predictions and pictures
(renders of test meshes, predicted beside ground truth, and the confusion matrix); the fold's model is the
run's MLflow logged model (meshseg.pyfunc). A `-m` sweep's fold runs are nested under its parent run.

A run's identity is `config_hash`: a config whose hash already has a FINISHED run is not run again,
so an interrupted sweep, rerun, does only what is missing. A run that raises ends FAILED with its
error text in the `error` tag; one interrupted from the keyboard ends KILLED; one killed outright
stays RUNNING and is marked KILLED when a later run of the same hash finishes.

One module per concern: `record` (what a fold's run records, and its names), `identity` (the config
hash), `provenance` (git commit, machine, versions, SLURM job), `store` (the store's uri, checks,
retries, interrupts, and `search_runs`), `lease` (claims' leases and heartbeats), `pictures` (the
renders), `tracker` (Tracker, one experiment in one store), `sweeps` (a sweep's parent run).
"""

from meshseg.tracking.identity import config_hash, flatten, fold_identity
from meshseg.tracking.lease import LEASE_HEARTBEAT, LEASE_INTERVAL, LEASE_OWNER, LEASE_TIMEOUT, Lease
from meshseg.tracking.provenance import git_sha, machine, system_tags, versions
from meshseg.tracking.record import SWEEP_KEY, FoldRecord, RunKey, is_fold_run
from meshseg.tracking.store import (
    STORE_SCHEMES,
    UI_URL,
    check_server,
    check_store_exists,
    interrupt,
    search_runs,
    store_uri,
    whole_call,
)
from meshseg.tracking.sweeps import close_parent, open_parent, sweep_key
from meshseg.tracking.tracker import Tracker

__all__ = [
    "LEASE_HEARTBEAT",
    "LEASE_INTERVAL",
    "LEASE_OWNER",
    "LEASE_TIMEOUT",
    "STORE_SCHEMES",
    "SWEEP_KEY",
    "UI_URL",
    "FoldRecord",
    "Lease",
    "RunKey",
    "Tracker",
    "check_server",
    "check_store_exists",
    "close_parent",
    "config_hash",
    "flatten",
    "fold_identity",
    "git_sha",
    "interrupt",
    "is_fold_run",
    "machine",
    "open_parent",
    "search_runs",
    "store_uri",
    "sweep_key",
    "system_tags",
    "versions",
    "whole_call",
]
