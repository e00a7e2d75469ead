"""Benchmarks (`meshsar bench`): radar, geometry, pipeline and trainer timings under build/bench/.

May import any subpackage.
"""
