"""The paper's baselines (§3.2-3.3, CF figure): pca_nn, ae_nn, ae_rf, rf.

Runs use five small synthetic figures (4 classes), a cheap feature set and budget=smoke, one thread;
the feature cache is shared by the session.
"""

import dataclasses

import numpy as np
import pytest
import torch
from mlflow import MlflowClient
from sklearn.decomposition import PCA
from test_run import compose_run

from meshseg.data.datasets import build_dataset
from meshseg.data.splits import Fold
from meshseg.features.sets import FeatureSet
from meshseg.models.forest import RandomForest
from meshseg.models.pca_nn import principal_axes
from meshseg.training.context import TrainContext
from meshseg.training.data import FeatureSource, build_train
from meshseg.training.fit import fit_predict
from meshseg.training.fitters import build_fitter

BASELINES = ["pca_nn", "ae_nn", "ae_rf", "rf"]
SMALL = [
    "dataset.meshes_per_category=5",
    "dataset.max_faces=3000",
    "features.groups=[curvature,pca,gc]",
    "features.name=local",
    "budget=smoke",
    "trainer.threads=1",
    "category=figure",
]
N_CLASSES = 4  # figure: head, torso, arm, leg
TRAIN = ("1", "2", "3")


@pytest.fixture(scope="module")
def paths(tmp_path_factory, cache_dir):
    """One MLflow store for the module's runs (creating a sqlite store takes seconds), the session's cache."""
    root = tmp_path_factory.mktemp("baselines")
    return [f"paths.mlflow_dir={root}/mlruns", f"paths.log_dir={root}/logs", f"paths.cache_dir={cache_dir}"]


def finished(paths, model):
    client = MlflowClient(f"sqlite:///{paths[0].split('=', 1)[1]}/mlflow.db")
    found = client.search_runs([client.get_experiment_by_name("meshseg").experiment_id], f"tags.model = '{model}'")
    return client, [r for r in found if r.info.status == "FINISHED"]


@pytest.fixture(scope="module")
def source(cache_dir):
    cfg = compose_run(*SMALL)
    return FeatureSource(build_dataset(cfg.dataset), "figure", FeatureSet.from_config(cfg.features), str(cache_dir), 1)


def fit(source, model, test=("0",), seed=0, *overrides):
    cfg = compose_run(*SMALL, f"model={model}", *overrides)
    ctx = TrainContext.from_config(cfg.budget, cfg.trainer, seed)
    fold_source = dataclasses.replace(source, fold=Fold(0, TRAIN, tuple(test)))
    return fit_predict(fold_source, build_fitter(cfg.model, ctx), cfg.budget.faces_per_mesh, workers=1)


# --- configuration --------------------------------------------------------------------------------


@pytest.mark.parametrize("model", BASELINES)
def test_each_baseline_is_single_scale_and_named(model):
    cfg = compose_run(f"model={model}")
    assert cfg.model.name == model and cfg.model.branches == 1 and cfg.branches == 1


def test_pca_nn_with_three_branches_is_rejected(tmp_path, cache_dir):
    from meshseg.run import run

    with pytest.raises(ValueError, match="branches=3 is not allowed with model=pca_nn: it takes branches=1"):
        run(
            compose_run(
                *SMALL, "model=pca_nn", "branches=3", f"paths.mlflow_dir={tmp_path}", f"paths.cache_dir={cache_dir}"
            )
        )
    assert list(tmp_path.iterdir()) == []  # refused before any run or store was made


def test_ae_rf_uses_the_autoencoders_of_ae_nn():
    assert compose_run("model=ae_rf").model.autoencoders == compose_run("model=ae_nn").model.autoencoders


def test_an_unknown_fitter_or_setting_is_one_error(source):
    with pytest.raises(ValueError, match=r"model=rf: cannot build meshseg.training.fitters.SVMFitter"):
        fit(source, "rf", ("0",), 0, "model._target_=meshseg.training.fitters.SVMFitter")
    with pytest.raises(ValueError, match=r"model=rf: meshseg.training.fitters.ForestFitter does not take .*'trees'"):
        fit(source, "rf", ("0",), 0, "+model.trees=5")


# --- the CLI path: every baseline ends FINISHED with a test accuracy --------------------------------


@pytest.mark.parametrize("model, extra", [("pca_nn", []), ("ae_nn", []), ("ae_rf", []), ("rf", ["features=cf0_5"])])
def test_baseline_runs_through_meshseg_run(paths, model, extra):
    from meshseg.run import run

    acc = run(compose_run(*SMALL, f"model={model}", "fold=0", *paths, *extra)).acc
    client, (r,) = finished(paths, model)
    assert r.data.tags["model"] == model and r.data.tags["branches"] == "1"
    assert np.isclose(r.data.metrics["test/acc"], acc) and 0 <= acc <= 1
    with np.load(client.download_artifacts(r.info.run_id, "predictions.npz")) as z:
        probs = z["probs_0"].astype(np.float32)  # 5fold: fold 0 tests mesh 0
    assert probs.shape[1] == N_CLASSES and np.allclose(probs.sum(axis=1), 1, atol=1e-2)
    curves = {k: [m.value for m in client.get_metric_history(r.info.run_id, k)] for k in r.data.metrics}
    if model.startswith("ae"):  # pre-training lowers each autoencoder's reconstruction error
        for stage in ("train/ae1_loss", "train/ae2_loss"):
            assert len(curves[stage]) == 2 and curves[stage][1] < curves[stage][0]
    if model == "ae_nn":
        assert len(curves["train/softmax_loss"]) == 2 and len(curves["train/loss"]) == 2
    if model == "rf":
        assert acc > 0.5  # CF features alone separate the figure's parts far better than chance (0.25)


# --- what each model computes ---------------------------------------------------------------------


def test_autoencoder_codes_have_400_then_200_columns_and_the_stack_is_fine_tuned_from_them(source):
    preds = fit(source, "ae_nn")
    ae1, ae2, net = preds.parts["ae1"], preds.parts["ae2"], preds.parts["net"]
    X = torch.from_numpy(build_train(source, TRAIN, 64, 0).X[:10])
    with torch.no_grad():
        assert ae1.encode(X).shape == (10, 400) and ae2.encode(ae1.encode(X)).shape == (10, 200)
        assert net.encode(X).shape == (10, 200) and net(X).shape == (10, N_CLASSES)
        assert torch.equal(net.encode(X), ae2.encode(ae1.encode(X)))  # one stack: the same encoder layers
    assert net.encoders[0] is ae1.encoder and net.encoders[1] is ae2.encoder


def test_pca_is_fitted_on_the_training_faces_only(source):
    a = fit(source, "pca_nn", ("0",)).parts["net"].pca
    b = fit(source, "pca_nn", ("4",)).parts["net"].pca
    assert torch.equal(a.mean, b.mean) and torch.equal(a.components, b.components)
    C = a.components.double()
    assert C.shape == (50, source.features.dim) and torch.allclose(
        C @ C.T, torch.eye(50, dtype=torch.float64), atol=1e-5
    )
    # the training faces as fit_predict sampled them (same seed and budget): scikit-learn's PCA of them
    X = build_train(source, TRAIN, 64, 0).X[:, 0]
    ref = PCA(50).fit(X.astype(np.float64))
    assert np.allclose(a.mean.numpy(), ref.mean_, atol=1e-5)
    top = ref.explained_variance_ratio_ > 1e-3  # well-separated axes: equal up to sign
    got, want = a.components.numpy()[top], ref.components_[top]
    assert np.allclose(np.abs((got * want).sum(axis=1)), 1, atol=1e-3)


def test_principal_axes_match_scikit_learn_and_refuse_too_many_components():
    rng = np.random.default_rng(0)
    X = (rng.normal(size=(500, 8)) * np.arange(1, 9)).astype(np.float32) + 3
    mean, axes = principal_axes(X, 3)
    ref = PCA(3).fit(X.astype(np.float64))
    assert np.allclose(mean, ref.mean_) and np.allclose(np.abs(axes @ ref.components_.T), np.eye(3), atol=1e-6)
    with pytest.raises(ValueError, match="PCA to 9 components needs at least that many features"):
        principal_axes(X, 9)


@pytest.mark.parametrize("model", BASELINES)
def test_probabilities_per_face_and_same_seed_same_output(source, model):
    first, again, other = fit(source, model), fit(source, model), fit(source, model, ("0",), 1)
    (p,) = first.probabilities
    assert p.dtype == np.float32 and p.shape == (first.meshes[0].n_faces, N_CLASSES)
    assert (p >= 0).all() and np.allclose(p.sum(axis=1), 1, atol=1e-5)
    assert np.array_equal(p, again.probabilities[0])
    assert not np.array_equal(p, other.probabilities[0])  # the seed is what makes them equal


def test_forest_gives_a_zero_column_to_a_class_it_never_saw():
    rng = np.random.default_rng(0)
    X, y = rng.normal(size=(60, 1, 3)).astype(np.float32), np.repeat([0, 2], 30)
    X[y == 2] += 3
    p = RandomForest(3, n_estimators=10, seed=0).fit(X, y).predict_proba(X)
    assert p.shape == (60, 3) and p.dtype == np.float32 and (p[:, 1] == 0).all()
    assert (p.argmax(axis=1) == y).all()
