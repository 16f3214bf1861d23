"""Per-face geometric features (paper §3.1): one module per family; importing the package
registers every group (see `registry.GROUPS`)."""

from meshseg.features import (  # noqa: F401  (imported for registration)
    agd,
    conformal,
    curvature,
    heat_kernel,
    medial,
    pca,
    shape_context,
    shape_diameter,
    spin_images,
)
