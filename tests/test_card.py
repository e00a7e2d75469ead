"""Dataset card renders line up with the SAR image grid (DESIGN section 3)."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
import trimesh

from meshsar_builder.dataset.card import cycle_plot, fitting_fov, render_views
from meshsar_builder.radar.params import view_frame

FOV, SIZE = 160.0, 128


@pytest.mark.parametrize("view", ["anterior", "left", "superior", "inferior"])
def test_render_puts_a_ball_where_the_image_grid_does(view):
    frame = view_frame(view)
    p = np.array([30.0, -20.0, 15.0])
    ball = trimesh.creation.icosphere(subdivisions=3, radius=8.0)
    (img,) = render_views(ball.vertices + p, ball.faces, None, [dict(zip("uvw", frame))], FOV, size=SIZE)
    rows, cols = np.nonzero(img.sum(axis=2) > 30)
    u, v = p @ frame[0], p @ frame[1]
    # pixel centre u = (col + 0.5 - W/2) fov/W, v = (H/2 - row - 0.5) fov/H
    expect_col = u / FOV * SIZE + SIZE / 2 - 0.5
    expect_row = SIZE / 2 - v / FOV * SIZE - 0.5
    assert abs(cols.mean() - expect_col) < 1.5 and abs(rows.mean() - expect_row) < 1.5
    # parallel projection at the image scale: the ball's disc is 2 r wide in pixels
    assert (cols.max() - cols.min() + 1) == pytest.approx(16.0 / FOV * SIZE, abs=2)


def test_cycle_plot_draws_volumes_and_motion_and_skips_unknown_phases(tmp_path):
    recs = [{"source": "bv", "subject": "p1", "cycle_fraction": t, "phase": ph, "apex_mm": [0.0, 0.0, 80.0 + d / 10],
             "base_mm": d, "structure_volumes_ml": {"lv": 140 - 4 * d, "rv": 160 - 4 * d, "myo": 120.0}}
            for t, ph, d in ((0.0, "ED", 0.0), (0.35, "ES", 14.0), (0.7, "", 4.0))]
    recs.append({**recs[1], "cycle_fraction": None, "phase": ""})  # a frame of a subject without NbFrame
    cycle_plot(recs, tmp_path / "cycle.png")
    image = plt.imread(tmp_path / "cycle.png")
    assert image.shape[1] > 1.8 * image.shape[0]  # two panels: volumes, and motion


def test_fitting_fov_shows_every_shape_whole_and_never_shrinks():
    frame = view_frame("anterior")
    view = dict(zip("uvw", frame))
    small = trimesh.creation.icosphere(radius=20.0).vertices
    large = trimesh.creation.box(extents=(200.0, 60.0, 120.0)).vertices
    assert fitting_fov([small], view, FOV) == FOV
    fov = fitting_fov([small, large], view, FOV)
    reach = np.abs(np.c_[large @ frame[0], large @ frame[1]]).max()
    assert fov / 2 >= reach
    (img,) = render_views(large, trimesh.creation.box(extents=(200.0, 60.0, 120.0)).faces, None, [view], fov, size=SIZE)
    lit = img.sum(axis=2) > 30
    # whole: nothing lit touches the picture's border
    assert lit.any() and not (lit[0].any() or lit[-1].any() or lit[:, 0].any() or lit[:, -1].any())
