"""A sweep's parent run (DESIGN "Tracking contract"): the fold runs of a `-m` sweep are nested under it (MLflow's
`mlflow.parentRunId` tag; the UI's runs table shows them under its row). A sweep's identity is its `sweep_key`,
a hash of its command line's settings, so a rerun of the sweep, resumed or not, finds its parent again and makes
no other, and two sweeps of one identity started at once agree on one parent. Parents are no folds: they carry
the SWEEP_KEY tag and no config hash, and every search for fold runs (Tracker.runs, search_runs) leaves them out.
"""

from __future__ import annotations

import hashlib
import json
import logging
import random
import time

from meshseg.errors import TrackingError
from meshseg.tracking.record import SWEEP_KEY
from meshseg.tracking.store import all_runs, retry

log = logging.getLogger(__name__)

#: attempts to make a parent that may meet parents made at the same moment
PARENT_ATTEMPTS = 40
#: the tag of a parent its maker kept (it saw no other): the only parents taken, as only they are never deleted
SWEEP_KEPT = "sweep_kept"
#: seconds after which a parent nobody kept is passed over (its maker died between making and deciding)
PENDING_S = 60


def sweep_key(overrides: list[str], exclude=()) -> tuple[str, list[str]]:
    """A sweep's identity (16 hex) and the overrides it hashes (in their order; hashed sorted): the command line's
    settings without Hydra's own (the launcher, the sweep's folder) and those in `exclude` (`tracking.hash_exclude`:
    the paths, the tracking settings, thread counts: what never changes a result); a key excludes its subtree."""
    prefixes = ("hydra", *exclude)

    def kept(override: str) -> bool:
        key = override.split("=", 1)[0].lstrip("+~")
        return not any(key == p or key.startswith((p + ".", p + "/")) for p in prefixes)

    settings = [o for o in overrides if kept(o)]
    return hashlib.sha256(json.dumps(sorted(settings)).encode()).hexdigest()[:16], settings


def parents(tracker, key: str) -> list:
    """The parent runs of sweep `key` in the tracker's experiment, kept or still being decided on (one, but for a
    moment when two are made)."""
    return all_runs(tracker.client, tracker.experiment_id, f"tags.{SWEEP_KEY} = '{key}'")


def _kept(run) -> bool:
    return run.data.tags.get(SWEEP_KEPT) == "true"


def _live(run) -> bool:
    """A parent kept, or one whose maker may still be deciding (one left undecided by a process that died is
    passed over once it is PENDING_S old)."""
    return _kept(run) or time.time() * 1000 - run.info.start_time < PENDING_S * 1000


def open_parent(tracker, key: str, name: str, tags: dict, params: dict) -> str:
    """The id of sweep `key`'s parent run, RUNNING: the one a run of this sweep kept before (its `tags` updated), or
    a new one named `name` with `tags` and `params`. No lock is needed: a new parent is kept (tagged SWEEP_KEPT)
    only if, once it is stored, no other live parent of the key is seen (of two made at once the later sees the
    earlier); parents that saw each other are deleted by their makers and made again after a random pause. A kept
    parent is never deleted, so only kept ones are taken; one still being decided on is waited for."""
    for attempt in range(PARENT_ATTEMPTS):
        found = [r for r in parents(tracker, key) if _live(r)]
        if kept := [r for r in found if _kept(r)]:
            return _resume(tracker, min(kept, key=lambda r: (r.info.start_time, r.info.run_id)).info.run_id, tags)
        if not found:
            mine = tracker._create(name, {**tags, SWEEP_KEY: key}).info.run_id
            if not [r for r in parents(tracker, key) if r.info.run_id != mine and _live(r)]:
                retry(lambda mine=mine: tracker.client.set_tag(mine, SWEEP_KEPT, "true"), "keep sweep")
                tracker.log_params(mine, params)
                return mine
            tracker.client.delete_run(mine)
        time.sleep(random.uniform(0.05, 0.25) * min(attempt + 1, 4))
    raise TrackingError(f"sweep {key}: {PARENT_ATTEMPTS} attempts in a row met other new parents; run it again")


def _resume(tracker, run_id: str, tags: dict) -> str:
    """A parent found again: its tags updated (e.g. the command line that reran it), RUNNING again."""
    _set_tags(tracker, run_id, tags)
    retry(lambda: tracker.client.update_run(run_id, status="RUNNING"), "resume sweep")
    return run_id


def _set_tags(tracker, run_id: str, tags: dict) -> None:
    for k, v in tags.items():
        retry(lambda k=k, v=v: tracker.client.set_tag(run_id, k, str(v)), "tag sweep")


def close_parent(tracker, run_id: str, metrics: dict[str, float], tags: dict, status: str) -> None:
    """End a sweep's parent run `status` (FINISHED, FAILED or KILLED), with what the sweep did as its `metrics`
    and `tags` (e.g. its summary in the description)."""
    tracker.log_metrics(run_id, metrics)
    _set_tags(tracker, run_id, tags)
    retry(lambda: tracker.client.set_terminated(run_id, status), "end sweep")
