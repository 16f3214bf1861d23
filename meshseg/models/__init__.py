"""Neural network models: the paper's multi-branch 1D CNN (`meshseg.models.cnn1d`)."""
