"""`python -m meshseg.results verify`: shipped records made again and compared, mesh by mesh.

    python -m meshseg.results verify [dir=results] [where=model=rf,category=Hand|Ant] [n=30] [seed=0]
                                     [tol=0.005] [attach=false] [add=false] [scratch=PATH] [out=reports/verify]

A record says which code, data, fold and settings produced it; verify checks that. The records under `dir`
whose tags match `where` (comma-separated tag=value pairs, a value's alternatives joined by `|`; none: all)
are chosen, and with `n` a seeded sample
of n of them, spread over methods and splits: each (model, split) group shuffled with `seed`, then taken in
turn. Each chosen record's run is made again by `python -m meshseg.run` from the record's own Hydra overrides
(its category and fold among them) into a scratch store (`scratch`, else a temporary one), and its per-mesh
accuracies are compared with the record's:

* identical: every test mesh's `acc` and `acc_raw` equal to the last bit;
* within:    the largest |Δ| at most `tol` (a fraction: 0.005 is half a point); the table's "max Δ" columns
             are the largest |Δ| of each accuracy over the record's test meshes;
* differs:   more than that;
* stale:     today's code gives the record's overrides and fold another config hash, so the same run
             cannot be made again (the record is reported, not re-made).

fp32 training is deterministic on one machine but not across instruction sets (AVX2 and AVX-512 round
differently), so a difference beside two different CPU lines is a finding, not a failure: the table
gives both machines. A run already in the scratch store at the record's config hash is compared, not made
again (so a verify cut short resumes with the same `scratch`). With `attach=true`, a record without per-face
labels whose run agrees (identical or within) gets the labels of the run made again, written into its file:
how the figures' runs from before records carried labels get them (experiments/figures_psb.yaml). The
table goes to `out` (verify.md, verify.csv), rewritten after each record; the command exits 1 when any
record differs or cannot be made again (failed). With `add=true` the table already at `out` is kept and
added to: the records it lists are not chosen again, so a sample grows over sessions and machines (each row
names the machine its run was made again on) instead of starting over when `dir` has gained records.
"""

from __future__ import annotations

import csv
import io
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from meshseg.errors import ConfigError
from meshseg.tracking import FoldRecord, Tracker, machine

#: the default largest per-mesh |Δ accuracy| (a fraction) still called "within"
TOLERANCE = 0.005
#: the per-mesh columns compared
COLUMNS = ("acc", "acc_raw")


@dataclass
class Outcome:
    path: Path
    record: dict
    status: str  # identical, within, differs, stale, failed
    delta: dict[str, float]  # column -> largest |Δ| over the test meshes (empty when not re-made)
    seconds: float
    why: str = ""
    attached: bool = False  # the record was given the labels of the run made again


def parse_where(text: str | None) -> dict[str, tuple[str, ...]]:
    """'model=rf,category=Hand|Ant' -> {'model': ('rf',), 'category': ('Hand', 'Ant')}."""
    out = {}
    for part in filter(None, (text or "").split(",")):
        key, sep, value = part.partition("=")
        values = tuple(v.strip() for v in value.split("|"))
        if not sep or not key or not all(values):
            raise ConfigError(f"where={text}: {part!r} is not tag=value[|value...] (e.g. where=model=rf,split=loo)")
        out[key.strip()] = values
    return out


def choose(records: list[tuple[Path, dict]], where: dict[str, tuple[str, ...]], n: int | None, seed: int):
    """The records matching `where`; with n, a seeded sample of n spread over (model, split) groups."""
    chosen = [(p, r) for p, r in records if all(str(r["tags"].get(k)) in v for k, v in where.items())]
    if n is None or n >= len(chosen):
        return chosen
    rng, groups = random.Random(seed), {}
    for p, r in sorted(chosen, key=lambda pr: str(pr[0])):
        groups.setdefault((r["tags"]["model"], r["tags"]["split"]), []).append((p, r))
    queues = [groups[k] for k in sorted(groups)]
    for q in queues:
        rng.shuffle(q)
    sample = []
    while len(sample) < n:
        for q in queues:
            if q and len(sample) < n:
                sample.append(q.pop())
    return sample


def compare(record_rows: list[dict], new_rows: list[dict], tol: float) -> tuple[str, dict[str, float]]:
    """The status and the largest |Δ| per column of two per-mesh tables of the same test meshes."""
    new = {row["mesh"]: row for row in new_rows}
    if set(new) != {row["mesh"] for row in record_rows}:
        return "differs", {}
    delta = {c: max(abs(float(row[c]) - float(new[row["mesh"]][c])) for row in record_rows) for c in COLUMNS}
    if all(d == 0 for d in delta.values()):
        return "identical", delta
    return ("within" if max(delta.values()) <= tol else "differs"), delta


def remake(record: dict, uri: str, log_dir: Path) -> str | None:
    """Run the record's fold again into the store at `uri`; None, or the failure's last lines."""
    overrides = json.loads(record["tags"]["overrides"])
    cmd = [sys.executable, "-m", "meshseg.run", *overrides, f"tracking.uri={uri}", "tracking.log_model=false"]
    cmd += ["tracking.renders=0", f"paths.log_dir={log_dir}"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    return None if proc.returncode == 0 else proc.stderr.strip()[-500:]


def per_mesh(tracker: Tracker, run) -> list[dict]:
    with tempfile.TemporaryDirectory(prefix="meshseg-verify-") as tmp:
        return FoldRecord.read_per_mesh(tracker.client.download_artifacts(run.info.run_id, FoldRecord.PER_MESH, tmp))


def verify(chosen, scratch: Path, tol: float = TOLERANCE, hashes=None, attach=None, progress=None) -> list[Outcome]:
    """Each chosen (path, record) made again in the store under `scratch` and compared. `hashes(record)` gives
    today's config hash of a record (meshseg.results.current_hash); `attach(tracker, run, path, record)`, if
    given, gives a record without labels those of its agreeing run (True if it did); `progress(outcomes, n)`
    is called after each record (default: print its line)."""
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # a bar per download otherwise
    uri = f"sqlite:///{scratch.resolve()}/mlflow.db"
    scratch.mkdir(parents=True, exist_ok=True)
    tracker = Tracker(uri, "meshseg", str(scratch.resolve() / "artifacts"))
    outcomes = []
    for path, record in chosen:
        start, h = time.perf_counter(), record["config_hash"]
        today = hashes(record) if hashes else h
        if today != h:
            out = Outcome(path, record, "stale", {}, 0.0, f"today's config hash {today}")
        else:
            run, failure = tracker.finished(h), None
            if run is None:  # not made in this scratch store yet
                failure = remake(record, uri, scratch / "logs")
                run = tracker.finished(h)
            if run is None:
                why = failure or "the run made again has another config hash"
                out = Outcome(path, record, "failed", {}, time.perf_counter() - start, why)
            else:
                status, delta = compare(record["per_mesh"], per_mesh(tracker, run), tol)
                out = Outcome(path, record, status, delta, time.perf_counter() - start)
                if attach and status in ("identical", "within") and not record.get("labels"):
                    out.attached = attach(tracker, run, path, record)
        outcomes.append(out)
        (progress or say)(outcomes, len(chosen))
    return outcomes


def say(outcomes: list[Outcome], n: int) -> None:
    """The progress line of the last record verified."""
    o = outcomes[-1]
    note = f" ({o.why})" if o.why else "; labels attached" if o.attached else ""
    print(f"verify {len(outcomes)}/{n}: {o.record['name']}: {o.status}{note}")


HEADER = (
    "record",
    "run",
    "model",
    "split",
    "set",
    "fold",
    "status",
    "max Δ acc",
    "max Δ acc_raw",
    "seconds",
    "labels",
    "made again on",
    "record's machine",
    "note",
)


def rows(outcomes: list[Outcome], root: Path) -> list[tuple]:
    """The table's rows (HEADER's columns, as text) of records verified on this machine."""
    here, out = machine("cpu"), []
    for o in outcomes:
        t = o.record["tags"]
        deltas = [f"{o.delta[c]:.2e}" if c in o.delta else "" for c in COLUMNS]
        rel = o.path.relative_to(root) if o.path.is_relative_to(root) else o.path
        out.append(
            (
                str(rel),
                o.record["name"],
                t["model"],
                t["split"],
                t["category"],
                t["fold"],
                o.status,
                *deltas,
                f"{o.seconds:.0f}",
                "attached" if o.attached else "yes" if o.record.get("labels") else "",
                here,
                t.get("machine", ""),
                o.why.replace("\n", " ").replace("|", "/"),
            )
        )
    return out


def summary(body: list[tuple]) -> str:
    """The outcome in words, from the table's rows (HEADER's columns)."""
    col = {name: i for i, name in enumerate(HEADER)}
    statuses = [r[col["status"]] for r in body]
    counts = {s: statuses.count(s) for s in ("identical", "within", "differs", "stale", "failed")}
    deltas = [float(r[col[c]]) for r in body for c in ("max Δ acc", "max Δ acc_raw") if r[col[c]]]
    attached = sum(r[col["labels"]] == "attached" for r in body)
    text = ", ".join(f"{v} {k}" for k, v in counts.items() if v) or "nothing chosen"
    text += f"; largest per-mesh |Δ| {max(deltas):.2e}" if deltas else ""
    return text + (f"; labels attached to {attached} records" if attached else "")


def read_table(out: Path) -> list[tuple]:
    """The rows of the table already at `out` (none if there is none): what `add=true` keeps and adds to."""
    path = out / "verify.csv"
    if not path.is_file():
        return []
    header, *body = list(csv.reader(io.StringIO(path.read_text(encoding="utf-8"))))
    if tuple(header) != HEADER or any(len(r) != len(HEADER) for r in body):
        raise ConfigError(f"{path}: not a verify table of today's columns ({', '.join(HEADER)}): give another out=")
    return [tuple(r) for r in body]


def listed(body: list[tuple]) -> set[str]:
    """The record files (relative to the records' folder) a table's rows name."""
    return {r[0] for r in body}


def choice_text(where: dict, n: int | None, seed: int) -> str:
    """What was chosen, in words: the filter and the sample."""
    text = ", ".join(f"{k}={'|'.join(v)}" for k, v in where.items()) or "every record"
    return text + (f", a sample of {n} (seed {seed})" if n else "")


def table_files(body: list[tuple], root: Path, tol: float, choice: str, chosen: int) -> dict[str, str]:
    """verify.md and verify.csv of the table's rows (`rows`, and those an `add=true` kept; `choice`: choice_text;
    `chosen`: how many rows the table has when this call's records are all done)."""
    buf = io.StringIO()
    csv.writer(buf).writerows([HEADER, *body])
    done = f" ({len(body)} of {chosen} done so far)" if len(body) < chosen else ""
    on = [r[HEADER.index("made again on")] for r in body] or [machine("cpu")]
    machines = "; ".join(f"{m} ({on.count(m)} records)" for m in dict.fromkeys(on)) if body else on[0]
    md = [
        "# Shipped records made again",
        "",
        f"Records: {choice} under `{root}`.{done}",
        f"Made again on: {machines}. Tolerance: per-mesh |Δ| <= {tol:g} is 'within'.",
        f"Outcome: {summary(body)}.",
        "",
        "| " + " | ".join(HEADER) + " |",
        "|" + "---|" * len(HEADER),
        *("| " + " | ".join(str(c) for c in r) + " |" for r in body),
        "",
    ]
    return {"verify.md": "\n".join(md), "verify.csv": buf.getvalue()}


def write_table(out: Path, files: dict[str, str]) -> None:
    """Each file written whole (a temporary name, then renamed)."""
    out.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        tmp = out / f".{name}.{os.getpid()}.tmp"
        tmp.write_text(text)
        tmp.replace(out / name)
