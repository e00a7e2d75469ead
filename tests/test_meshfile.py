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
    # the same bytes as plyfile's own (row by row) writer, so a reader of either kind reads the file
    from plyfile import PlyData, PlyElement

    vertex = np.empty(n, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")] + [("label", "u1")] * with_labels)
    vertex["x"], vertex["y"], vertex["z"] = verts.T
    if with_labels:
        vertex["label"] = labels
    face = np.empty(m, dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = faces
    reference = path.parent / "reference.ply"
    elements = [PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")]
    PlyData(elements, text=False).write(str(reference))
    assert path.read_bytes() == reference.read_bytes()


def test_quads_and_truncated_files_are_named(tmp_path):
    """The fast triangle read falls back to plyfile's general one, which names what is wrong."""
    import pytest
    from plyfile import PlyData, PlyElement

    from meshsar_builder.pipeline.errors import InputError

    vertex = np.zeros(4, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    quad = np.empty(1, dtype=[("vertex_indices", "i4", (4,))])
    quad["vertex_indices"] = [0, 1, 2, 3]
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(quad, "face")], text=False).write(
        str(tmp_path / "quad.ply"))
    with pytest.raises(InputError, match="quad.ply: faces must be triangles"):
        read_ply(tmp_path / "quad.ply")
    write_ply(tmp_path / "whole.ply", np.zeros((5, 3)), np.array([[0, 1, 2], [2, 3, 4]]))
    data = (tmp_path / "whole.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-7])
    with pytest.raises(InputError, match="cut.ply: not a readable PLY mesh .*early end-of-file"):
        read_ply(tmp_path / "cut.ply")
