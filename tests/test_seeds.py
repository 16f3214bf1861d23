"""A manifest column run at several training seeds (`seeds:`): its cells, what reproduce launches, the claims.
The statistics (intervals over seeds and folds) are tested on hand-made columns in tests/test_claims.py."""

import shutil

import numpy as np
import pytest
import yaml
from conftest import REPO, SMOKE, smoke_env

from meshseg.errors import ManifestError
from meshseg.report.aggregate import Bootstrap
from meshseg.report.claims import judge
from meshseg.report.claims_file import Claim
from meshseg.report.manifest import load_manifest
from meshseg.report.table import collect
from meshseg.reproduce import missing_cells, reproduce
from meshseg.tracking import search_runs

RF = ["model=rf"]


def manifest(tmp_path, columns) -> object:
    doc = yaml.safe_load((REPO / "experiments/synthetic.yaml").read_text())
    doc |= {"name": "seeded", "columns": columns}
    for g in doc["groups"]:  # one set: a sweep per seed is a process start, the slow part
        g["published_average"] = [None] * len(columns)
        g["sets"] = [dict(s, published=[None] * len(columns)) for s in g["sets"] if s["name"] == "Cup"]
    path = tmp_path / "seeded.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_seeds_must_be_distinct_whole_numbers_on_a_column_of_runs(tmp_path):
    for seeds, why in (([0, 0], "distinct whole numbers"), ([-1], "distinct whole numbers"), ("0", "distinct")):
        path = manifest(tmp_path, [{"key": "r", "label": "R", "overrides": RF, "seeds": seeds}])
        with pytest.raises(ManifestError, match=f"column r: seeds: give a list of {why}"):
            load_manifest(path)
    path = manifest(tmp_path, [{"key": "p", "label": "P", "overrides": None, "seeds": [0]}])
    with pytest.raises(ManifestError, match="only a column of runs has training seeds"):
        load_manifest(path)


def test_a_column_at_two_seeds_is_the_mean_over_them_and_a_missing_seed_is_not_yet_run(
    smoke_store, tmp_path, cache_dir, monkeypatch
):
    """On a copy of the smoke store (RF at seed 0): `seeds: [0]` is the plain column, hash for hash; `seeds:
    [0, 1]` lacks seed 1 everywhere (not yet run, one sweep per set at seed=1); reproduce makes those runs,
    and the cell is then the mean over the seeds, with their spread."""
    store = tmp_path / "store"
    shutil.copytree(smoke_store, store / "mlruns")
    for k, v in smoke_env(store, cache_dir).items():
        monkeypatch.setenv(k, v)
    columns = [
        {"key": "rf", "label": "RF", "overrides": RF},
        {"key": "rf0", "label": "RF seed 0", "overrides": RF, "seeds": [0]},
        {"key": "rf01", "label": "RF seeds 0, 1", "overrides": RF, "seeds": [0, 1]},
    ]
    path = manifest(tmp_path, columns)
    table = collect(load_manifest(path), SMOKE, boot=Bootstrap(200))
    for row in (r for r in table.rows if r.kind == "set"):
        plain, zero, both = row.cells
        assert (zero.value, zero.config_hashes) == (plain.value, plain.config_hashes)  # (each key seeds its CI)
        assert zero.seed_values == () and zero.status == "ok"
        assert both.status == "incomplete" and both.missing_runs == ((1, 0), (1, 1)) and both.short() == "— (2/4 runs)"
    sweeps = [m for m in missing_cells(table) if m.column == "rf01"]
    assert [(m.row, m.overrides[-1], m.folds) for m in sweeps] == [("Cup", "seed=1", (0, 1))]
    verdict = judge(Claim("s", "t", "", "seeded", "rf01", "rf"), table)
    assert (verdict.verdict, verdict.missing_runs) == ("not yet run", 2)

    args = [*SMOKE, "report.columns=[rf01,rf]", "report.results=null", "report.log=false"]
    done = reproduce(path, [*args, f"report.out_dir={tmp_path / 'reports'}"])
    assert [(c.column, c.folds) for c in done.launched] == [("rf01", (0, 1))] and not done.failed
    table = collect(load_manifest(path), SMOKE, boot=Bootstrap(200))
    meshes = table.meshes
    for row in (r for r in table.rows if r.kind == "set"):
        plain, _, both = row.cells
        own = meshes[(meshes["row"] == row.label) & (meshes["column"] == "rf01")]
        per_seed = own.groupby("seed")["acc"].mean()
        assert sorted(own["seed"].unique()) == [0, 1] and len(both.config_hashes) == 4
        assert both.value == pytest.approx(per_seed.mean()) and both.seed_values == pytest.approx(tuple(per_seed))
        assert per_seed[0] == pytest.approx(plain.value)  # seed 0's runs are the plain column's
        assert both.seed_sd == pytest.approx(float(np.std(per_seed, ddof=1)))
    avg = next(r for r in table.rows if r.kind == "average").cells[2]
    assert avg.seed_values == pytest.approx(table.rows[0].cells[2].seed_values)  # the mean over its one set
    verdict = judge(Claim("s", "t", "", "seeded", "rf01", "rf"), table)
    assert verdict.seeds == 1 and verdict.verdict != "not yet run"  # rf has one seed: the fewest
    runs = search_runs(f"sqlite:///{store}/mlruns/mlflow.db", "meshseg")
    names = {r.data.tags["seed"]: r.info.run_name for r in runs}
    assert names["1"].endswith("· seed 1") and "seed" not in names["0"]  # the UI tells a fold's seeds apart
