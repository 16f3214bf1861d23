"""Golden run identities. Shipped results (results/) are found by config hash: a change that moves
one of these hashes orphans every logged run of that config. If this test fails, either undo the
change or make it deliberately: update the hashes here and say in docs/changelog.md why results
made before must be redone."""

import pytest
from hydra import compose, initialize_config_dir

from meshseg import CONF_DIR
from meshseg.data.splits import Fold
from meshseg.tracking import fold_identity

FOLD = Fold(0, ("1", "2", "3", "4"), ("5",))
DATA = "0123456789abcdef0123456789abcdef"  # a stand-in content hash: the test needs no data

GOLDEN = {
    "cnn1d 3B cpu psb": (["dataset=psb", "budget=cpu"], "Airplane"),
    "cnn1d 1B f600 cpu psb": (["dataset=psb", "budget=cpu", "branches=1", "features=f600"], "Airplane"),
    "cnn2d cpu psb": (["dataset=psb", "budget=cpu", "model=cnn2d"], "Teddy"),
    "rf cf0_5 loo psb": (["dataset=psb", "budget=cpu", "model=rf", "features=cf0_5", "split=loo"], "Chair"),
    "cnn1d 3B paper fixed psb": (["dataset=psb", "budget=paper", "split=fixed"], "Airplane"),
}


def identity(overrides, category):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("run", overrides=overrides)
    return fold_identity(cfg, category, FOLD, DATA)[1]


HASHES = {
    "cnn1d 3B cpu psb": "1609f512c85ffa65",
    "cnn1d 1B f600 cpu psb": "b35110850fa78cef",
    "cnn2d cpu psb": "da8ef0a91639f165",
    "rf cf0_5 loo psb": "221311ee1bcd0f57",
    "cnn1d 3B paper fixed psb": "10c5049956c6d7fd",
}


@pytest.mark.parametrize("name", list(GOLDEN))
def test_golden_config_hashes_stay_put(name):
    overrides, category = GOLDEN[name]
    assert identity(overrides, category) == HASHES[name], (
        f"the run identity of '{name}' changed: see this file's docstring"
    )


def test_what_is_not_a_knob_keeps_the_hash(monkeypatch, tmp_path):
    overrides, category = GOLDEN["cnn1d 3B cpu psb"]
    base = identity(overrides, category)
    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(tmp_path))
    moved = [
        *overrides,
        "dataset.root=/elsewhere/psb",
        "trainer.threads=1",
        "workers=1",
        f"tracking.uri=sqlite:///{tmp_path}/x.db",
        "tracking.renders=0",
        "trainer.predict_batch_size=64",
    ]
    assert identity(moved, category) == base
    assert identity([*overrides, "seed=1"], category) != base
    assert identity([*overrides, "refine=none"], category) != base


def test_a_knob_at_its_hash_default_keeps_the_hash_and_any_other_value_moves_it():
    """budget.resample, split.seed and refine.search came after runs were shipped: at their defaults the hash is the one
    the golden table holds; set away from them, the run is another config."""
    base = identity(["dataset=psb", "budget=cpu"], "Airplane")
    assert base == HASHES["cnn1d 3B cpu psb"]
    assert identity(["dataset=psb", "budget=cpu", "budget.resample=fold", "split.seed=null"], "Airplane") == base
    assert identity(["dataset=psb", "budget=cpu", "budget.resample=epoch"], "Airplane") != base
    assert identity(["dataset=psb", "budget=cpu", "split.seed=1"], "Airplane") != base
    assert identity(["dataset=psb", "budget=cpu", "refine.search=null"], "Airplane") == base
    assert identity(["dataset=psb", "budget=cpu", "refine.search={lam:[1.0,2.0]}"], "Airplane") != base


def test_budget_cpu2_is_cpu_trained_in_bf16_and_a_run_of_its_own():
    """cpu2 (the budget study's adoption) sets trainer.precision through budget.precision; cpu's runs keep their
    identity, and a cpu2 run is neither a cpu run nor the study's `cpu` + `trainer.precision=bf16-mixed` run."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cpu2, cpu = compose("run", overrides=["dataset=psb", "budget=cpu2"]), compose("run", overrides=["dataset=psb"])
    assert (cpu2.trainer.precision, cpu.trainer.precision) == ("bf16-mixed", "32-true")
    assert {k: v for k, v in cpu2.budget.items() if k not in ("name", "precision")} == {
        k: v for k, v in cpu.budget.items() if k != "name"
    }
    base = identity(["dataset=psb", "budget=cpu"], "Airplane")
    moved = identity(["dataset=psb", "budget=cpu2"], "Airplane")
    study = identity(["dataset=psb", "budget=cpu", "trainer.precision=bf16-mixed"], "Airplane")
    assert len({base, moved, study}) == 3 and base == HASHES["cnn1d 3B cpu psb"]


def test_a_number_has_one_identity_however_the_command_line_types_it():
    """refine.lam=2 is the default 2.0 and budget.epochs=15.0 the default 15: the same config hash (as the report
    and `meshseg.results` compose it; `meshseg.run`'s skip is in tests/test_run.py). 2.5 is another value."""
    from meshseg.config import run_config

    def composed(*overrides):
        return fold_identity(run_config(["dataset=psb", "budget=cpu", *overrides]), "Airplane", FOLD, DATA)

    base = composed()[1]
    assert base == HASHES["cnn1d 3B cpu psb"]
    config, moved = composed("refine.lam=2")
    assert moved == base and type(config["refine"]["lam"]) is float
    config, epochs = composed("budget.epochs=15.0")
    assert epochs == base and type(config["budget"]["epochs"]) is int
    assert composed("budget.epochs=16.0")[1] == composed("budget.epochs=16")[1] != base
    assert composed("refine.lam=2.5")[1] != base
    assert composed("budget.epochs=15.5")[0]["budget"]["epochs"] == 15.5  # not exact as an integer: left as typed
    # the last override of a key decides, as in Hydra (a manifest's value, then the command line's)
    assert composed("refine.lam=2", "refine.lam=2.5")[0]["refine"]["lam"] == 2.5
    assert composed("budget.epochs=15.0", "budget.epochs=7")[0]["budget"]["epochs"] == 7
    assert "lam" not in composed("refine.lam=2", "~refine.lam")[0]["refine"]


def test_a_config_is_composed_once_a_process_and_each_caller_gets_its_own_copy(monkeypatch):
    """run_config composes each overrides once (a report asks for a column's config three times); a caller that
    changes its copy changes no later caller's config, and other overrides are composed for themselves."""
    import hydra

    from meshseg.config import _composed, run_config

    calls = []
    compose = hydra.compose
    monkeypatch.setattr(hydra, "compose", lambda *a, **k: calls.append(k["overrides"]) or compose(*a, **k))
    _composed.cache_clear()
    first = run_config(["dataset=psb", "model=cnn2d"])
    first.model.name = "changed by a caller"
    again = run_config(["dataset=psb", "model=cnn2d"])
    assert again.model.name == "cnn2d" and again is not first
    assert calls == [["dataset=psb", "model=cnn2d"]]
    assert run_config(["dataset=psb", "model=gbdt"]).model.name == "gbdt" and len(calls) == 2
