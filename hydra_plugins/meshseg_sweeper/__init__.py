"""Hydra plugin: meshseg's sweeper (hydra/sweeper=meshseg)."""
