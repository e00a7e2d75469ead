"""PLY round trips: what is written is read back exactly."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from meshsar_builder.geometry.meshfile import read_ply, write_ply


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(3, 60),
    m=st.integers(0, 80),
    with_labels=st.booleans(),
    data=st.data(),
)
def test_ply_round_trip_is_exact(tmp_path_factory, n, m, with_labels, data):
    verts = data.draw(arrays(np.float64, (n, 3), elements=st.floats(-1e4, 1e4, allow_nan=False)))
    faces = data.draw(arrays(np.int64, (m, 3), elements=st.integers(0, n - 1)))
    labels = data.draw(arrays(np.uint8, n)) if with_labels else None
    path = tmp_path_factory.mktemp("ply") / "mesh.ply"
    write_ply(path, verts, faces, labels)
    v, f, lab = read_ply(path)
    assert v.tobytes() == verts.tobytes() and np.array_equal(f, faces.reshape(-1, 3))
    assert (lab is None) if labels is None else np.array_equal(lab, labels)
    assert [p.name for p in path.parent.iterdir()] == ["mesh.ply"]  # no temporary left
