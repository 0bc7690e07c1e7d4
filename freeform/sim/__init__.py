"""Voxelyze's soft-voxel physics in Taichi (see docs/architecture.md)."""
