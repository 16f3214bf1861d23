"""Split protocols: LOO, dealt 5-fold, and ShapePFCN's published fixed lists."""

import re

import pytest
from conftest import SPLIT_FILE, require
from omegaconf import OmegaConf

from meshseg.data.datasets import Synthetic
from meshseg.data.mesh import MeshDataError
from meshseg.data.splits import FixedSplit, KFold, LeaveOneOut, folds_for, kfold, leave_one_out, read_split_file
from meshseg.errors import ConfigError

IDS = [str(i) for i in range(61, 81)]


def test_leave_one_out():
    folds = leave_one_out(IDS)
    assert len(folds) == 20
    for i, f in enumerate(folds):
        assert f.test == (IDS[i],) and len(f.train) == 19 and IDS[i] not in f.train


def test_kfold_deals_sorted_ids():
    folds = kfold(reversed(IDS), 5)
    assert [f.test for f in folds][:2] == [("61", "66", "71", "76"), ("62", "67", "72", "77")]
    tests = [m for f in folds for m in f.test]
    assert sorted(tests) == sorted(IDS) and len(set(tests)) == 20
    for f in folds:
        assert len(f.test) == 4 and set(f.train) == set(IDS) - set(f.test)
    assert [len(f.test) for f in kfold([str(i) for i in range(12)], 5)] == [3, 3, 2, 2, 2]
    with pytest.raises(ValueError, match="between 2 and 3 folds"):
        kfold(["1", "2", "3"], 5)


def test_kfold_with_a_seed_deals_another_seeded_assignment():
    folds = kfold(IDS, 5, seed=1)
    assert [f.test for f in folds] == [f.test for f in kfold(reversed(IDS), 5, seed=1)]  # by id, then the seed
    assert [f.test for f in folds] != [f.test for f in kfold(IDS, 5)]  # not the default dealing
    assert [f.test for f in folds] != [f.test for f in kfold(IDS, 5, seed=2)]
    tests = [m for f in folds for m in f.test]
    assert sorted(tests) == sorted(IDS) and [len(f.test) for f in folds] == [4] * 5
    for f in folds:
        assert list(f.test) == sorted(f.test, key=int) and set(f.train) == set(IDS) - set(f.test)
    with pytest.raises(ConfigError, match=r"split.seed=-1 is not allowed"):
        KFold(5, seed=-1)


def test_fixed_split_psb_published_ids(psb):
    split_file = require(SPLIT_FILE)
    (fold,) = FixedSplit(split_file).folds(psb, "Airplane")
    assert fold.train == ("61", "62", "64", "66", "67", "69", "71", "72", "74", "76", "77", "79")
    assert fold.test == ("63", "65", "68", "70", "73", "75", "78", "80")
    blocks = read_split_file(str(split_file))
    for category in psb.categories:
        (fold,) = FixedSplit(split_file).folds(psb, category)
        assert (len(fold.train), len(fold.test)) == (12, 8), category
        train, test = blocks[f"psb{category}"]
        assert set(fold.train) == {m.removeprefix("model") for m in train}
        assert set(fold.test) == {m.removeprefix("model") for m in test}


def test_split_file_blocks():
    blocks = read_split_file(str(require(SPLIT_FILE)))
    assert len(blocks) == 16 + 19 + 11
    assert [len(x) for x in blocks["cosegTeleAliens"]] == [12, 188]


def test_fixed_split_errors(coseg, tmp_path):
    split_file = require(SPLIT_FILE)
    # the fragment lacks most of the published COSEG chairs
    with pytest.raises(MeshDataError, match=r"block cosegChairs names \d+ meshes the dataset lacks"):
        FixedSplit(split_file).folds(coseg, "chairs")
    with pytest.raises(ValueError, match="no lists for dataset 'synthetic'"):
        FixedSplit(split_file).folds(Synthetic(meshes_per_category=2), "cup")
    bad = tmp_path / "s.txt"
    bad.write_text("Category psbCup\nTraining split: 3 shapes\nmodel1\nmodel2\nTest split: 1 shapes\n")
    with pytest.raises(MeshDataError, match=re.escape("block psbCup: training list declares 3 shapes but holds 2")):
        read_split_file(str(bad))
    bad.write_text("Category psbCup\nmodel1\n")
    with pytest.raises(MeshDataError, match=re.escape("line 2: expected 'Training split: N shapes' in block psbCup")):
        read_split_file(str(bad))


def test_protocols_are_classes_named_in_their_yaml():
    ds = Synthetic(categories=["cup"], meshes_per_category=7)
    assert len(LeaveOneOut().folds(ds, "cup")) == 7
    assert [len(f.test) for f in KFold(5).folds(ds, "cup")] == [2, 2, 1, 1, 1]
    assert (LeaveOneOut().name, KFold(5).name, KFold(3).name, FixedSplit("x").name) == (
        "loo",
        "5fold",
        "3fold",
        "fixed",
    )
    # a config names its class; the folds are the class's
    three = OmegaConf.create({"_target_": "meshseg.data.splits.KFold", "k": 3})
    assert [f.test for f in folds_for(ds, "cup", three)] == [f.test for f in KFold(3).folds(ds, "cup")]
    with pytest.raises(ValueError, match=r"split: cannot build meshseg.data.splits.Holdout"):
        folds_for(ds, "cup", OmegaConf.create({"_target_": "meshseg.data.splits.Holdout"}))
    with pytest.raises(
        ValueError, match=r"split: meshseg.data.splits.KFold does not take .*\['fraction', 'k'\]: .*'fraction'"
    ):
        folds_for(ds, "cup", OmegaConf.create({"_target_": "meshseg.data.splits.KFold", "k": 3, "fraction": 0.2}))
    with pytest.raises(ValueError, match=r"split.k=1 is not allowed"):
        KFold(1)
    with pytest.raises(ValueError, match="split=fixed needs split.file"):
        FixedSplit(None)
