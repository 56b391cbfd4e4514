"""Synthetic dynamic RGB-D scenes with per-pixel ground truth (motion masks, instance ids, static mesh)."""
