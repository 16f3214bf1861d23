"""The models' settings as a `conf/model/*.yaml` node gives them, typed and checked when the method is
built (`meshseg.training.fitters.build_fitter`), before any feature is computed: a value out of range is
one `ConfigError` naming the setting as the user writes it, e.g.
`model.net.hidden=-1 is not allowed: it must be an integer >= 1`.

Each class is a frozen dataclass whose defaults are the shipped YAML's values; `Cls.of(values)` builds
one from the node's keys (an unknown key is refused too). The networks keep the checks that need the
data's sizes (feature count, branches): those are known only when the fold's network is built.
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Mapping, Sequence
from typing import ClassVar

from torch import nn

from meshseg.errors import ConfigError

#: activation layers of the fully connected baselines (pca_nn, the autoencoders), by name
ACTIVATIONS = {
    "tanh": nn.Tanh,
    "relu": nn.ReLU,
    "sigmoid": nn.Sigmoid,
    "leaky_relu": nn.LeakyReLU,
    "linear": nn.Identity,
}
CNN2D_ACTIVATIONS = ("relu", "leaky_relu", "tanh", "sigmoid")
PADDINGS = ("same", "valid")
MAX_FEATURES = ("sqrt", "log2")


def show(value) -> str:
    """A value as it is written on the command line: [16, 32], null, true, gelu."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return value
    if isinstance(value, Sequence) or _is_list(value):
        return "[" + ", ".join(show(v) for v in value) + "]"
    return str(value)


def _is_list(value) -> bool:
    return hasattr(value, "__iter__") and not isinstance(value, str | Mapping)


def _is_int(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


@dataclasses.dataclass(frozen=True)
class Settings:
    """Base of the settings classes: `of` builds one from a config node, the `_check_*` helpers check
    one field each (and store it normalised) or raise the one-line error."""

    prefix: ClassVar[str] = "model.net"

    @classmethod
    def of(cls, values: Mapping) -> Settings:
        """The settings a config node (or a dict of keywords) gives; keys that are no setting are refused."""
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(str(k) for k in values if k not in names)
        if unknown:
            raise ConfigError(f"{cls.prefix}.{unknown[0]} is not a setting of {cls.prefix}: it takes {names}")
        return cls(**values)

    def refuse(self, name: str, rule: str, value=dataclasses.MISSING) -> ConfigError:
        value = getattr(self, name) if value is dataclasses.MISSING else value
        return ConfigError(f"{self.prefix}.{name}={show(value)} is not allowed: {rule}")

    def _store(self, name: str, value) -> None:
        object.__setattr__(self, name, value)  # normalising a frozen dataclass's field in __post_init__

    def _check_int(self, name: str, minimum: int = 1, optional: bool = False) -> None:
        value = getattr(self, name)
        if optional and value is None:
            return
        if not (_is_int(value) and value >= minimum):
            raise self.refuse(name, f"it must be an integer >= {minimum}" + (" or null" if optional else ""))
        self._store(name, int(value))

    def _check_ints(self, name: str, pair: bool = False, may_be_empty: bool = False) -> None:
        """A list of integers >= 1: a non-empty one, an empty one too (may_be_empty), or two (pair)."""
        value = getattr(self, name)
        values = list(value) if _is_list(value) else None
        ok = values is not None and all(_is_int(v) and v >= 1 for v in values)
        if not ok or (len(values) != 2 if pair else not (values or may_be_empty)):
            what = "a pair [height, width]" if pair else "a list" if may_be_empty else "a non-empty list"
            raise self.refuse(name, f"it must be {what} of integers >= 1")
        self._store(name, tuple(int(v) for v in values))

    def _check_number(self, name: str, low: float, high: float | None = None) -> None:
        """A number in [low, high) (no upper bound when high is None)."""
        value = getattr(self, name)
        ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
        if not (ok and low <= value and (high is None or value < high)):
            rule = f">= {low:g}" if high is None else f"in [{low:g}, {high:g})"
            raise self.refuse(name, f"it must be a number {rule}")
        self._store(name, float(value))

    def _check_fraction(self, name: str) -> None:
        """A number in (0, 1]."""
        value = getattr(self, name)
        if not (isinstance(value, numbers.Real) and not isinstance(value, bool) and 0 < value <= 1):
            raise self.refuse(name, "it must be a number in (0, 1]")
        self._store(name, float(value))

    def _check_choice(self, name: str, options: Sequence[str]) -> None:
        if getattr(self, name) not in options:
            raise self.refuse(name, f"choose one of {list(options)}")

    def _check_bool(self, name: str) -> None:
        if not isinstance(getattr(self, name), bool):
            raise self.refuse(name, "it must be true or false")


@dataclasses.dataclass(frozen=True)
class CNN1DSettings(Settings):
    """The multi-branch 1D CNN's settings (conf/model/cnn1d.yaml `net:`; the architecture they shape is
    described in meshseg/models/cnn1d.py): the paper's values by default. Both implementations,
    `PaperCNN1D` and `MultiBranchCNN1D`, take these and nothing else."""

    max_branches: ClassVar[int] = 4  # the paper evaluates 1-4 branches (§4)

    channels: Sequence[int] = (16, 32)  # output channels of each convolution stage
    kernels: Sequence[int] = (15, 11)  # its kernel length
    hidden: int = 172  # the first fully connected layer's width
    negative_slope: float = 0.2  # LeakyReLU's; >= 0: the fast network pools before it (monotonic)
    dropout: float = 0.5
    pool: int = 2  # max pooling after each stage

    def __post_init__(self):
        self._check_ints("channels")
        self._check_ints("kernels")
        if len(self.kernels) != len(self.channels):
            raise self.refuse("kernels", f"it must give one size per entry of {self.prefix}.channels")
        self._check_int("hidden")
        self._check_number("negative_slope", 0.0)
        self._check_number("dropout", 0.0, 1.0)
        self._check_int("pool")

    def out_length(self, n_features: int, branches: int) -> int:
        """The length of each branch's last map for inputs of `n_features`; refuses inputs too short for
        the poolings and branch counts outside 1..max_branches."""
        if not (_is_int(branches) and 1 <= branches <= self.max_branches):
            raise ConfigError(f"branches={branches} is not allowed: the 1D CNN takes 1..{self.max_branches}")
        length = int(n_features)
        for _ in self.channels:
            length //= self.pool
        if length < 1:
            raise ConfigError(
                f"{n_features} features are too few for {len(self.channels)} poolings by {self.pool}: "
                f"choose fewer {self.prefix}.channels or a smaller {self.prefix}.pool"
            )
        return length


@dataclasses.dataclass(frozen=True)
class CNN2DSettings(Settings):
    """ToG15's 2D CNN settings (conf/model/cnn2d.yaml `net:`, meshseg/models/cnn2d.py). A kernel is an
    integer k (k x k) or a pair [height, width]; both are stored as pairs."""

    image_shape: Sequence[int] = (30, 20)
    channels: Sequence[int] = (16, 32)
    kernels: Sequence = ((7, 5), (5, 5))
    padding: str = "same"
    pool: int = 2
    hidden: int = 128
    activation: str = "relu"
    negative_slope: float = 0.2
    batch_norm: bool = True
    dropout: float = 0.5

    def __post_init__(self):
        self._check_ints("image_shape", pair=True)
        self._check_ints("channels")
        self._check_kernels()
        self._check_choice("padding", PADDINGS)
        self._check_int("pool")
        self._check_int("hidden")
        self._check_choice("activation", CNN2D_ACTIVATIONS)
        self._check_number("negative_slope", 0.0)
        self._check_bool("batch_norm")
        self._check_number("dropout", 0.0, 1.0)
        if self.padding == "same" and any(k % 2 == 0 for pair in self.kernels for k in pair):
            raise self.refuse("kernels", f"{self.prefix}.padding=same needs odd kernel sizes (centred filters)")
        self.map_shape()

    def map_shape(self) -> tuple[int, int]:
        """The (height, width) of the last pooled map; refuses an image too small for the layers."""
        h, w = self.image_shape
        for kh, kw in self.kernels:
            if self.padding == "valid":
                h, w = h - kh + 1, w - kw + 1
            h, w = h // self.pool, w // self.pool
            if min(h, w) < 1:
                raise self.refuse(
                    "image_shape",
                    f"it is too small for {len(self.channels)} '{self.padding}' convolutions "
                    f"{show(self.kernels)} each followed by {self.pool}x{self.pool} pooling",
                )
        return h, w

    def _check_kernels(self) -> None:
        rule = f"it must list one size k or [height, width] (integers >= 1) per entry of {self.prefix}.channels"
        if not _is_list(self.kernels) or len(list(self.kernels)) != len(self.channels):
            raise self.refuse("kernels", rule)
        pairs = []
        for k in self.kernels:
            pair = (k, k) if _is_int(k) else tuple(k) if _is_list(k) else ()
            if len(pair) != 2 or not all(_is_int(v) and v >= 1 for v in pair):
                raise self.refuse("kernels", rule)
            pairs.append((int(pair[0]), int(pair[1])))
        self._store("kernels", tuple(pairs))


@dataclasses.dataclass(frozen=True)
class PCANetSettings(Settings):
    """The PCA & NN baseline's settings (conf/model/pca_nn.yaml `net:`, meshseg/models/pca_nn.py)."""

    n_components: int = 50
    hidden: Sequence[int] = (50, 25, 12)
    activation: str = "tanh"

    def __post_init__(self):
        self._check_int("n_components")
        self._check_ints("hidden", may_be_empty=True)
        self._check_choice("activation", list(ACTIVATIONS))


@dataclasses.dataclass(frozen=True)
class ForestSettings(Settings):
    """A random forest's settings (conf/model/rf.yaml and ae_rf.yaml `forest:`, meshseg/models/forest.py):
    scikit-learn RandomForestClassifier's, with the paper's 100 trees."""

    prefix: ClassVar[str] = "model.forest"

    n_estimators: int = 100
    max_features: str | float | int | None = "sqrt"
    min_samples_leaf: int = 1
    max_depth: int | None = None
    bootstrap: bool = True

    def __post_init__(self):
        self._check_int("n_estimators")
        self._check_max_features()
        self._check_int("min_samples_leaf")
        self._check_int("max_depth", optional=True)
        self._check_bool("bootstrap")

    def _check_max_features(self) -> None:
        value = self.max_features
        if value is None or value in MAX_FEATURES or (_is_int(value) and value >= 1):
            return
        if isinstance(value, float) and 0 < value <= 1:
            return
        raise self.refuse(
            "max_features", f"choose one of {list(MAX_FEATURES)}, null, an integer >= 1 or a fraction in (0, 1]"
        )


GBDT_LIBRARIES = ("lightgbm",)


@dataclasses.dataclass(frozen=True)
class GbdtSettings(Settings):
    """Gradient-boosted trees' settings (conf/model/gbdt.yaml `trees:`, meshseg/models/gbdt.py; not in the
    paper). The YAML gives the reason for each default."""

    prefix: ClassVar[str] = "model.trees"

    library: str = "lightgbm"
    max_rounds: int = 1000
    learning_rate: float = 0.1
    num_leaves: int = 31
    min_child_samples: int = 20
    feature_fraction: float = 0.3
    bagging_fraction: float = 0.8
    lambda_l2: float = 1.0
    max_bin: int = 63
    early_stopping_rounds: int = 30
    inner_meshes: float = 0.2
    refit: bool = True

    def __post_init__(self):
        self._check_choice("library", GBDT_LIBRARIES)
        self._check_int("max_rounds")
        self._check_fraction("learning_rate")
        self._check_int("num_leaves", minimum=2)
        self._check_int("min_child_samples")
        self._check_fraction("feature_fraction")
        self._check_fraction("bagging_fraction")
        self._check_number("lambda_l2", 0.0)
        self._check_int("max_bin", minimum=2)
        self._check_int("early_stopping_rounds")
        self._check_number("inner_meshes", 0.0, 1.0)
        if self.inner_meshes == 0.0:
            raise self.refuse("inner_meshes", "it must be a fraction in (0, 1): the meshes early stopping holds out")
        self._check_bool("refit")
