"""The dataset: sources (label-map loaders), shards and index, splits, verify, PyTorch readers, the card.

Imports `pipeline`, `geometry` and `radar`; never `trainer`.
"""
