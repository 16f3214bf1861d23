"""Per-face geometric features (paper §3.1)."""
