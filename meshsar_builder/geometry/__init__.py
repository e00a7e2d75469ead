"""Geometry: label maps to meshes, remeshing, registration, the shape model, phantoms, mesh files.

Imports `pipeline` only. Functions take and return arrays (`verts : (n, 3) float` mm,
`faces : (F, 3) int`); no stage bookkeeping here.
"""
