"""Points along junction rings (geometry/landmarks.py): counted in the ring's affine-normalised
plane, and turned to follow a neighbour's ring."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from meshsar_builder.geometry.landmarks import (
    RING_BINS,
    RING_MAX_TURN_DEG,
    _best_turn,
    _region_moments,
    label_landmarks,
)
from tests.test_tracking import bent_cone


def test_ring_points_move_with_an_affine_motion_in_the_rings_plane():
    """The cone's full ring below its la patch lies near a plane z = const (the crossing edges'
    midpoints spread about an edge's height); a map that shears and stretches those planes
    unevenly (keeping z) moves each of its points with the surface, to within what that spread
    tilts the ring's plane: at most 0.15 mm. Counted by plain angle about the ring's centre (the
    rule before the normalisation) the same points slid along the ring by up to 1.9 mm (mean 1.1)."""
    verts, faces, labels = bent_cone()
    marks = label_landmarks(verts, faces, labels, ring_points=8)
    affine = np.array([[1.3, 0.25, 0.0], [-0.1, 0.85, 0.0], [0.0, 0.0, 1.0]])
    moved = verts @ affine.T + np.array([4.0, -2.0, 7.0])
    again = label_landmarks(moved, faces, labels, ring_points=8)
    closed = [k for k in marks.keys if k.startswith("ring:lv-myo@")]  # the full ring below the la patch
    assert len(closed) == 8, marks.keys
    expected = marks.select(closed).points(verts) @ affine.T + np.array([4.0, -2.0, 7.0])
    assert np.linalg.norm(again.select(closed).points(moved) - expected, axis=1).max() < 0.3


def _profile(seed: int, turn_deg: float) -> np.ndarray:
    """A smooth radius profile (RING_BINS,) of random harmonics, its origin turned by turn_deg."""
    rng = np.random.default_rng(seed)
    theta = np.linspace(-np.pi, np.pi, RING_BINS, endpoint=False) - np.radians(turn_deg)
    k = np.arange(1, 6)
    return 1.0 + (rng.normal(0, 0.08, 5) / k * np.cos(np.outer(theta, k) + rng.uniform(0, 2 * np.pi, 5))).sum(axis=1)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), turn=st.floats(-RING_MAX_TURN_DEG + 2, RING_MAX_TURN_DEG - 2))
def test_best_turn_recovers_a_turned_profile_between_degrees(seed, turn):
    like = _profile(seed, 0.0)
    if np.std(like) < 0.02 * np.mean(like):
        return  # too round to follow: the next test
    assert abs(np.degrees(_best_turn(_profile(seed, turn), like)) - turn) < 0.05


def test_best_turn_is_none_for_a_round_ring_a_changed_one_or_beyond_its_limit():
    flat = np.ones(RING_BINS)
    assert _best_turn(flat + 1e-3 * np.sin(np.linspace(0, 2 * np.pi, RING_BINS)), flat) == 0.0
    single = 1.0 + 0.2 * np.exp(-0.5 * (np.linspace(-180, 180, RING_BINS, endpoint=False) / 10) ** 2)  # one bump
    assert abs(np.degrees(_best_turn(np.roll(single, 10), single)) - 10.0) < 0.05
    assert _best_turn(np.roll(single, int(RING_MAX_TURN_DEG) + 15), single) == 0.0
    theta = np.radians(np.linspace(-180, 180, RING_BINS, endpoint=False))
    changed = np.roll(single, 10) + 0.03 * np.cos(3 * theta)  # turned, and a new shape on top
    assert _best_turn(changed, single) == 0.0
    assert abs(np.degrees(_best_turn(np.roll(single, 10) + 0.005 * np.cos(3 * theta), single)) - 10.0) < 0.5


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_region_moments_whiten_an_affine_image_alike(seed):
    """The fan region's moments move with an affine map: whitened, a ring and its image differ by
    a rotation only (the points' radii agree), even where the map spaces the points unevenly."""
    rng = np.random.default_rng(seed)
    angle = np.sort(rng.uniform(-np.pi, np.pi, 60))
    ring = np.c_[np.cos(angle), np.sin(angle)] * (1 + 0.2 * np.cos(3 * angle + rng.uniform(0, 6)))[:, None] * 20
    matrix = np.eye(2) + rng.uniform(-0.4, 0.4, (2, 2))
    image = ring @ matrix.T + rng.uniform(-50, 50, 2)
    (centre, root), (image_centre, image_root) = _region_moments(ring), _region_moments(image)
    np.testing.assert_allclose(image_centre, centre @ matrix.T + (image - ring @ matrix.T)[0], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm((image - image_centre) @ image_root, axis=1),
                               np.linalg.norm((ring - centre) @ root, axis=1), rtol=1e-9)


def test_region_moments_of_a_straight_junction_stay_finite():
    line = np.c_[np.linspace(0, 40, 30), np.zeros(30)]
    centre, root = _region_moments(line)
    assert np.isfinite(centre).all() and np.isfinite(root).all()
