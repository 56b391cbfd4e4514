"""Tracking and mapping (bundle adjustment) against the neural map."""
