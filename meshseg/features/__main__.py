"""Compute and cache a feature set.

python -m meshseg.features dataset=psb dataset.root=PATH features=f800 [category=Airplane] [workers=2]
python -m meshseg.features mesh=FILE.off out=FILE.npy features=f800
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from meshseg import CONF_DIR
from meshseg.cli import user_errors
from meshseg.data.datasets import build_dataset
from meshseg.data.io import atomic_write, check_output_folder, read_mesh
from meshseg.errors import ConfigError
from meshseg.features.cache import FeatureCache
from meshseg.features.sets import FeatureSet, check_finite, compute_dataset


def save_npy(path: str, X: np.ndarray) -> None:
    """Atomic .npy write: a killed run never leaves a half file under the requested name."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"out={path} is a folder; name the .npy file to write")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise ConfigError(f"out={path}: its folder {p.parent} cannot be created (a file is in the way)") from None
    atomic_write(p, lambda fh: np.save(fh, X))


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="features")
def main(cfg: DictConfig) -> None:
    with user_errors():  # a user error is one line; anything else is a bug, with its traceback
        fs = FeatureSet.from_config(cfg.features)
        cache_root = cfg.paths.cache_dir if cfg.cache else None
        if cfg.mesh is not None:
            if cfg.out is None:
                raise ConfigError("mesh=FILE needs out=FILE.npy")
            if Path(cfg.out).is_dir():  # checked before the features are computed, not after
                raise ConfigError(f"out={cfg.out} is a folder; name the .npy file to write")
            check_output_folder(Path(cfg.out).parent, "out's folder")  # made if missing, so it must be makeable
            mesh = read_mesh(cfg.mesh)
            t0 = time.perf_counter()
            X = fs.compute(mesh.vertices, mesh.faces, mesh.content_hash, FeatureCache(cache_root))
            check_finite(X, fs, mesh.source)  # never write NaN: the dataset path refuses such a mesh too
            save_npy(cfg.out, X)
            print(f"{cfg.out}: {X.shape[0]} x {X.shape[1]} float32 ({fs.name}) in {time.perf_counter() - t0:.1f} s")
            return
        dataset = build_dataset(cfg.dataset)
        categories = [dataset.check_category(cfg.category)] if cfg.category else dataset.categories
        compute_dataset(dataset, fs, cache_root, [(c, m) for c in categories for m in dataset.mesh_ids(c)], cfg.workers)


if __name__ == "__main__":
    main()
