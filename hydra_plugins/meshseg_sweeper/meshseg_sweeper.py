"""Hydra's basic sweeper, plus: a job whose overrides do not fix `category` runs every category of
its dataset, and one that does not fix `fold` every fold of its split (folds differ per category
under leave-one-out, so this is not a Cartesian product Hydra could express)."""

from dataclasses import dataclass
from typing import Dict, List, Optional

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.config_store import ConfigStore
from hydra.core.override_parser.types import Override


@dataclass
class MeshsegSweeperConf:
    _target_: str = "hydra_plugins.meshseg_sweeper.meshseg_sweeper.MeshsegSweeper"
    max_batch_size: Optional[int] = None
    params: Optional[Dict[str, str]] = None


ConfigStore.instance().store(group="hydra/sweeper", name="meshseg", node=MeshsegSweeperConf, provider="meshseg")


class MeshsegSweeper(BasicSweeper):
    def split_arguments(self, overrides: List[Override], max_batch_size: Optional[int]) -> List[List[List[str]]]:
        from meshseg.run import sweep_cells

        jobs = []
        for combo in BasicSweeper.split_arguments(overrides, None)[0]:
            keys = {o.split("=", 1)[0].lstrip("+~") for o in combo}
            cfg = self.hydra_context.config_loader.load_sweep_config(self.config, list(combo))
            for category, fold in sweep_cells(cfg, "category" in keys, "fold" in keys):
                jobs.append([*combo, *([f"category={category}"] if category is not None else []),
                             *([f"fold={fold}"] if fold is not None else [])])
        return list(BasicSweeper.split_overrides_to_chunks(jobs, max_batch_size))
