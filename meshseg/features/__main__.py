"""Compute and cache a feature set.

    python -m meshseg.features dataset=psb dataset.root=PATH features=f800 [category=Airplane] [workers=2]
    python -m meshseg.features mesh=FILE.off out=FILE.npy features=f800
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from meshseg import CONF_DIR
from meshseg.data.datasets import MeshDataset, build_dataset
from meshseg.data.io import read_obj, read_off
from meshseg.data.mesh import Mesh, MeshDataError
from meshseg.features.cache import FeatureCache
from meshseg.features.sets import FeatureSet


def load_mesh_file(path: str) -> Mesh:
    p = Path(path)
    if p.suffix.lower() == ".obj":
        v, f, _, _ = read_obj(p)
    elif p.suffix.lower() == ".off":
        v, f = read_off(p)
    else:
        raise MeshDataError(p, "unknown mesh format (expected .off or .obj)")
    return Mesh(v, f, source=str(p))


def _one(dataset: MeshDataset, category: str, mesh_id: str, fs: FeatureSet, cache_root: str | None):
    t0 = time.perf_counter()
    mesh = dataset.load(category, mesh_id)
    X = fs.compute(mesh.vertices, mesh.faces, mesh.content_hash, FeatureCache(cache_root))
    if not np.isfinite(X).all():
        bad = sorted({fs.columns[j] for j in np.flatnonzero(~np.isfinite(X).all(axis=0))})
        raise FloatingPointError(f"{mesh.source}: non-finite features in columns {bad[:5]}")
    return category, mesh_id, mesh.n_faces, time.perf_counter() - t0


def compute_dataset(dataset: MeshDataset, fs: FeatureSet, cache_root: str | None, categories: list[str],
                    workers: int = 2, out=sys.stdout) -> tuple[int, int, float]:
    """Every mesh of `categories`, `workers` meshes at a time; one line per mesh, then the total."""
    from joblib import Parallel, delayed
    from tqdm import tqdm

    jobs = [(c, m) for c in categories for m in dataset.mesh_ids(c)]
    t0 = time.perf_counter()
    n_faces = 0
    results = Parallel(n_jobs=workers, return_as="generator_unordered")(
        delayed(_one)(dataset, c, m, fs, cache_root) for c, m in jobs)
    with tqdm(total=len(jobs), unit="mesh", file=sys.stderr, disable=None) as bar:
        for category, mesh_id, faces, seconds in results:
            n_faces += faces
            bar.update()
            bar.write(f"{category}/{mesh_id}: {faces} faces in {seconds:.1f} s ({faces / seconds:.0f} faces/s)", file=out)
    elapsed = time.perf_counter() - t0
    print(f"features: {len(jobs)} meshes, {n_faces} faces, {n_faces / elapsed:.0f} faces/s", file=out)
    return len(jobs), n_faces, elapsed


def save_npy(path: str, X: np.ndarray) -> None:
    """Atomic .npy write: a killed run never leaves a half file under the requested name."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=f".{p.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.save(fh, X)
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="features")
def main(cfg: DictConfig) -> None:
    try:
        fs = FeatureSet.from_config(cfg.features)
        cache_root = cfg.paths.cache_dir if cfg.cache else None
        if cfg.mesh is not None:
            if cfg.out is None:
                raise ValueError("mesh=FILE needs out=FILE.npy")
            mesh = load_mesh_file(cfg.mesh)
            t0 = time.perf_counter()
            X = fs.compute(mesh.vertices, mesh.faces, mesh.content_hash, FeatureCache(cache_root))
            save_npy(cfg.out, X)
            print(f"{cfg.out}: {X.shape[0]} x {X.shape[1]} float32 ({fs.name}) in {time.perf_counter() - t0:.1f} s")
            return
        dataset = build_dataset(cfg.dataset)
        categories = [dataset.check_category(cfg.category)] if cfg.category else dataset.categories
        compute_dataset(dataset, fs, cache_root, categories, cfg.workers)
    except (MeshDataError, ValueError, FloatingPointError) as e:
        sys.exit(f"error: {e}")


if __name__ == "__main__":
    main()
