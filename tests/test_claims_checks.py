"""A claims file checked in full when it is loaded (issue 48): a key outside the schema at any level, a margin,
threshold or share that is no number or out of range, thresholds the wrong way round, a `tables:` entry without a
label, a claim comparing a column with itself, a list given as a bare string, and a claim naming a table that is no
manifest. Each is one error naming the file, the claim or entry, and the problem; no table is built."""

import copy
import re
import shutil

import pytest
import yaml
from conftest import REPO
from test_manifest_checks import quiet

from meshseg.cli import ERROR_EXIT
from meshseg.errors import ManifestError
from meshseg.report.app import main as report_main
from meshseg.report.claims_file import load_claims
from meshseg.report.config import check_config, compose_config
from meshseg.report.manifest import load_manifest

#: a claims file on experiments/synthetic.yaml (copied beside it), with every key a claims file takes
CLAIMS = {
    "name": "claims",
    "title": "t",
    "rule": "r",
    "overrides": [],
    "thresholds": {"full": 1.0, "partial": 2.0},
    "tables": [{"table": "synthetic", "label": "Synthetic", "group": "synthetic"}],
    "budget_study": {"table": "synthetic", "compare": {"3B": [["1B", "3B"]]}},
    "claims": [
        {"id": "1", "text": "3B beats RF", "source": "s", "table": "synthetic", "a": "3B", "b": "rf", "sets": ["Cup"]},
        {"id": "5a", "text": "3B as 1B", "table": "synthetic", "a": "3B", "b": "1B", "test": "equal", "margin": 0.5},
        {"id": "6", "text": "most", "table": "synthetic", "a": "1B", "b": "rf", "test": "most_sets", "min_share": 0.5},
        {"id": "7", "text": "refined", "table": "synthetic", "a": "3B", "test": "refinement", "models": ["3B"]},
    ],
}
CLAIM_KEYS = "id, text, source, table, a, b, test, sets, group, margin, min_share, models"


def claims_file(tmp_path, edit=None):
    """CLAIMS edited by `edit` (a function of a copy of it) as tmp_path/claims.yaml, experiments/synthetic.yaml
    beside it."""
    doc = copy.deepcopy(CLAIMS)
    if edit:
        edit(doc)
    shutil.copy(REPO / "experiments/synthetic.yaml", tmp_path / "synthetic.yaml")
    path = tmp_path / "claims.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def claim(doc, i: int) -> dict:
    return doc["claims"][i]


def test_the_unedited_claims_file_loads_and_so_does_the_shipped_one(tmp_path):
    c = load_claims(claims_file(tmp_path))
    assert (c.full, c.partial, c.claims[1].margin, c.claims[2].min_share) == (1.0, 2.0, 0.5, 0.5)
    assert c.claims[0].sets == ("Cup",) and c.claims[3].models == ("3B",) and c.tables[0].group == "synthetic"
    check_config(compose_config("report", claims_file(tmp_path)))
    check_config(compose_config("report", REPO / "experiments/claims.yaml"))  # every table it names is there


@pytest.mark.parametrize(
    "edit, problem",
    [
        # keys outside the schema, at every level
        (
            lambda d: d.update(treshold={"full": 1.0}),
            "unknown key 'treshold': a claims file takes name, title, rule, overrides, thresholds, tables, "
            "budget_study, claims",
        ),
        (
            lambda d: claim(d, 1).update(margn=claim(d, 1).pop("margin")),
            f"claims[1] (5a): unknown key 'margn': a claim takes {CLAIM_KEYS}",
        ),
        (
            lambda d: d["tables"][0].update(gruop=d["tables"][0].pop("group")),
            "tables[0]: unknown key 'gruop': a tables entry takes table, label, group",
        ),
        (
            lambda d: d["thresholds"].update(partal=3.0),
            "thresholds: unknown key 'partal': thresholds takes full, partial",
        ),
        (
            lambda d: d["budget_study"].update(fold_list={}),
            "budget_study: unknown key 'fold_list': budget_study takes table, compare, fold_lists, floor_table, "
            "floor_columns",
        ),
        # numbers: no string read as one, none out of range
        (
            lambda d: claim(d, 1).update(margin="0.5"),
            "claims[1] (5a): margin='0.5' is not allowed: it must be a number of points > 0",
        ),
        (
            lambda d: claim(d, 1).update(margin=-0.5),
            "claims[1] (5a): margin=-0.5 is not allowed: it must be a number of points > 0",
        ),
        (
            lambda d: d["thresholds"].update(full="1"),
            "thresholds.full='1' is not allowed: it must be a number of points > 0",
        ),
        (
            lambda d: d["thresholds"].update(partial=float("nan")),
            "thresholds.partial=nan is not allowed: it must be a number of points > 0",
        ),
        (
            lambda d: d.update(thresholds={"full": 3.0, "partial": 2.0}),
            "thresholds: full=3 is more than partial=2: full is the stricter threshold (every run column within "
            "it), so full <= partial",
        ),
        (
            lambda d: claim(d, 2).update(min_share=1.5),
            "claims[2] (6): min_share=1.5 is not allowed: it must be a share > 0 and <= 1 (0.75: three sets in four)",
        ),
        # shapes
        (
            lambda d: d["tables"][0].pop("label"),
            "tables[0]: needs table and label, got {'table': 'synthetic', 'group': 'synthetic'}",
        ),  # fmt: skip
        (
            lambda d: claim(d, 0).update(b="3B"),
            "claims[0] (1): a and b are both column '3B'; a claim compares two columns",
        ),
        (
            lambda d: claim(d, 0).update(sets="Table"),
            "claims[0] (1): sets='Table' is not allowed: give a list of set names, e.g. [Fish, Teddy]",
        ),
        (
            lambda d: claim(d, 3).update(models="3B"),
            "claims[3] (7): models='3B' is not allowed: give a list of the budget study's models, e.g. [3B]",
        ),
        (
            lambda d: claim(d, 3).update(models=["5B"]),
            "claims[3] (7): models ['5B'] have no budget_study.compare entry; it compares 3B",
        ),
        (
            lambda d: d.update(overrides="budget=cpu"),
            "overrides='budget=cpu' is not allowed: give a list of run overrides, e.g. [budget=cpu]",
        ),
        (lambda d: d["budget_study"].pop("table"), "budget_study: needs table, the budget study's manifest"),
        (
            lambda d: d["budget_study"].update(compare=[["1B", "3B"]]),
            "budget_study.compare: expected {model: [[a, b], ...]}, got [['1B', '3B']]",
        ),
    ],
    ids=[
        "top-key",
        "claim-key",
        "tables-key",
        "thresholds-key",
        "budget-study-key",
        "string-margin",
        "negative-margin",
        "string-threshold",
        "nan-threshold",
        "reversed-thresholds",
        "min-share-over-1",
        "tables-without-label",
        "a-is-b",
        "sets-string",
        "models-string",
        "unknown-model",
        "overrides-string",
        "budget-study-without-table",
        "compare-not-a-mapping",
    ],
)
def test_a_bad_claims_file_is_refused_naming_the_claim_and_the_problem(tmp_path, edit, problem):
    path = claims_file(tmp_path, edit)
    with pytest.raises(ManifestError, match=f"^{re.escape(f'{path}: {problem}')}$"):
        load_claims(path)


def test_a_claim_naming_no_manifest_is_named_before_any_table_is_built(tmp_path):
    path = claims_file(tmp_path, lambda d: claim(d, 2).update(table="synthetc"))
    load_claims(path)  # the file alone is well formed: the manifests beside it are checked with the settings
    problem = (
        f"{path}: claims[2] (6): table 'synthetc' is no manifest (no {tmp_path / 'synthetc'}.yaml); "
        "the manifests beside it: synthetic"
    )
    with pytest.raises(ManifestError, match=f"^{re.escape(problem)}$"):
        check_config(compose_config("report", path))
    path = claims_file(tmp_path, lambda d: d["tables"][0].update(table="table9"))
    with pytest.raises(ManifestError, match=re.escape(f"{path}: tables[0]: table 'table9' is no manifest")):
        check_config(compose_config("report", path))


@pytest.mark.parametrize(
    "edit, problem",
    [
        (lambda d: claim(d, 2).update(table="synthetc"), "claims[2] (6): table 'synthetc' is no manifest"),
        (lambda d: claim(d, 1).update(margin=-0.5), "claims[1] (5a): margin=-0.5 is not allowed"),
        (lambda d: d["tables"][0].pop("label"), "tables[0]: needs table and label"),
    ],
    ids=["unknown-table", "negative-margin", "tables-without-label"],
)
def test_a_bad_claims_file_is_one_error_line_before_hydra(tmp_path, monkeypatch, capsys, edit, problem):
    path = claims_file(tmp_path, edit)
    with pytest.raises(SystemExit) as e:
        report_main([str(path), *quiet(tmp_path, monkeypatch)])
    err = capsys.readouterr().err.strip()
    assert e.value.code == ERROR_EXIT and len(err.splitlines()) == 1, err
    assert err.startswith(f"error: {path}: {problem}"), err
    assert not (tmp_path / "logs").exists()  # refused before Hydra makes the command's log folder


def test_a_claims_file_given_as_a_manifest_says_so():
    """meshseg.reproduce reads its argument as a study manifest: a claims file is named as such."""
    path = REPO / "experiments/claims.yaml"
    problem = (
        f"{path}: a claims file, not a study manifest (meshseg.report judges its claims on the manifests it names)"
    )
    with pytest.raises(ManifestError, match=f"^{re.escape(problem)}$"):
        load_manifest(path)
