"""meshseg: reproduction harness for George, Xie & Tam (2018), 3D mesh segmentation via multi-branch 1D CNNs."""

from pathlib import Path

__version__ = "0.1.0"

#: Hydra configuration root (`conf/` beside the package; the project is installed editable).
CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")
