"""Meshes, labels, datasets and splits."""
