"""`python -m meshseg.data dataset=NAME [dataset.root=PATH]`: one row per category, then the total."""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from meshseg import CONF_DIR
from meshseg.cli import user_errors
from meshseg.data.datasets import MeshDataset, build_dataset


def summarize(dataset: MeshDataset, out=sys.stdout) -> tuple[int, int]:
    """Load and validate every mesh; print meshes, faces, labels and zero-area faces per category."""
    print(f"{'category':<16}{'meshes':>7}{'faces':>11}{'labels':>7}{'zero-area':>10}", file=out)
    n_meshes = n_faces = 0
    for category in dataset.categories:
        meshes = faces = degenerate = 0
        for mesh in dataset.meshes(category):
            meshes += 1
            faces += mesh.n_faces
            degenerate += mesh.n_degenerate
        print(
            f"{category:<16}{meshes:>7}{faces:>11}{len(dataset.label_names(category)):>7}{degenerate:>10}",
            file=out,
            flush=True,
        )
        n_meshes, n_faces = n_meshes + meshes, n_faces + faces
    print(f"total: {n_meshes} meshes, {n_faces} faces", file=out)
    return n_meshes, n_faces


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="data")
def main(cfg: DictConfig) -> None:
    with user_errors():
        summarize(build_dataset(cfg.dataset))


if __name__ == "__main__":
    main()
