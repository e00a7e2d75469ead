"""The reference SAR2Mesh trainer: model, losses, metrics, training and evaluation.

Imports `pipeline`, `geometry`, `radar` (the differentiable echo) and `dataset` (the
readers). Nothing in the builder imports it.
"""
