"""Evaluation: ATE, mesh accuracy/completion, motion-mask IoU, tables and plots."""
