"""Masks to meshes against analytic surfaces (DESIGN section 6)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import ndimage
from skimage.measure import euler_number

from meshsar_builder.geometry.meshing import (
    MeshingParams,
    is_closed_genus0,
    labels_to_surface,
    long_axis_landmarks,
    resample_cubic,
    signed_distance,
    trim_vessels,
)
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import InputError, MeshError

from .conftest import ball_volume

LV = STRUCTURES["lv"]


def mesh_of(mask, affine, params=MeshingParams()):
    s = labels_to_surface(mask.astype(np.uint8) * LV, affine, ["lv"], params)
    return s, trimesh.Trimesh(s.verts, s.faces, process=False)


def ellipsoid_area(a, b, c):
    """Area of an ellipsoid from a finely subdivided icosphere (relative error < 1e-4)."""
    sphere = trimesh.creation.icosphere(subdivisions=7)
    return sphere.apply_scale((a, b, c)).area


@pytest.mark.parametrize(
    "voxel, vol_tol, area_tol",
    [((1.0, 1.0, 1.0), 0.01, 0.03), ((1.5, 1.5, 8.0), 0.04, 0.04)],
)
def test_sphere_volume_and_area(voxel, vol_tol, area_tol):
    r = 30.0
    shape = np.ceil(90 / np.asarray(voxel)).astype(int)
    mask, affine = ball_volume(shape, voxel, r)
    s, m = mesh_of(mask, affine)
    assert m.is_watertight and m.euler_number == 2
    assert abs(m.volume / (4 / 3 * np.pi * r**3) - 1) < vol_tol
    assert abs(m.area / (4 * np.pi * r**2) - 1) < area_tol
    np.testing.assert_allclose(m.bounds.mean(axis=0), 0, atol=0.3 * max(voxel))


@pytest.mark.parametrize(
    "voxel, vol_tol, area_tol",
    [((1.0, 1.0, 1.0), 0.01, 0.03), ((1.5, 1.5, 8.0), 0.04, 0.04)],
)
def test_ellipsoid_volume_and_area(voxel, vol_tol, area_tol):
    axes = (35.0, 25.0, 45.0)
    shape = np.ceil(110 / np.asarray(voxel)).astype(int)
    mask, affine = ball_volume(shape, voxel, None, axes_mm=axes)
    _, m = mesh_of(mask, affine)
    assert abs(m.volume / (4 / 3 * np.pi * np.prod(axes)) - 1) < vol_tol
    assert abs(m.area / ellipsoid_area(*axes) - 1) < area_tol


def test_outward_normals_and_world_position():
    """Off-centre ball under a flipped, offset affine: mesh lands at the world centre, normals out."""
    mask, affine = ball_volume((60, 60, 60), (1, 1, 1), 15, centre_mm=(5, -8, 3))
    flipped = affine @ np.array([[-1, 0, 0, 59], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    _, m = mesh_of(mask[::-1], flipped)
    np.testing.assert_allclose(m.bounds.mean(axis=0), (5, -8, 3), atol=0.5)
    assert m.volume > 0
    outward = np.einsum("ij,ij->i", m.face_normals, m.triangles_center - m.center_mass)
    assert (outward > 0).mean() > 0.99


def test_signed_distance_zero_halfway_between_voxels():
    mask = np.zeros((9, 9, 9), bool)
    mask[:5] = True
    sd = signed_distance(mask, np.array([2.0, 1.0, 1.0]))
    # inside voxel next to the boundary is half a step in, outside neighbour half a step out
    assert sd[4, 4, 4] == pytest.approx(-2.0) and sd[5, 4, 4] == pytest.approx(2.0)


def test_torus_with_small_hole_is_filled():
    """A ring whose hole (4 mm across) survives smoothing: the repair fills the hole, the cheaper
    change, and says where."""
    coords = np.arange(60) - 29.5
    X, Y, Z = np.meshgrid(coords, coords, coords, indexing="ij")
    rho = np.hypot(X, Y)
    mask = (rho - 10.0) ** 2 + Z**2 <= 8.0**2
    assert not mask[30, 30, 30]  # a real hole
    s, m = mesh_of(mask, np.eye(4))
    assert m.is_watertight and m.euler_number == 2
    (handle,) = s.repair["handles"]
    assert handle["kind"] == "fill" and handle["structures"] == ["lv"]
    np.testing.assert_allclose(handle["position_mm"], (29.5, 29.5, 29.5), atol=1.0)  # the hole's centre
    assert s.repair["euler_before"] == 0 and abs(s.repair["volume_change"]["lv"]) < 0.01


def test_torus_whose_repair_is_too_large_fails_with_figures():
    """A thick ring around a wide hole: cutting it (the cheaper change) takes 2.3 % of its volume."""
    coords = np.arange(80) - 39.5
    X, Y, Z = np.meshgrid(coords, coords, coords, indexing="ij")
    mask = (np.hypot(X, Y) - 25.0) ** 2 + Z**2 <= 6.0**2
    with pytest.raises(MeshError, match=r"topology repair too large: volume change \{'lv': -0\.0\d+\} \(limit 2%\).*"
                                        r"Euler characteristic before 0; labels cleaned: none; walls filled: none; "
                                        r"contacts cut: none; handles: \['cut \d+ vox at"):
        mesh_of(mask, np.eye(4))
    s, m = mesh_of(mask, np.eye(4), MeshingParams(max_volume_change=0.05))
    assert m.is_watertight and m.euler_number == 2 and s.repair["handles"][0]["kind"] == "cut"


def test_a_repair_failure_names_every_step_the_repair_took():
    """A failed item writes no sidecar: its message is the only record of what the repair did (a real cine frame
    named "contacts cut: none; handles: none" while 3 myocardium holes and a 282-voxel wall had moved it)."""
    from meshsar_builder.geometry.label_repair import repair_summary as _summary

    record = {"euler_before": -12, "labels": {"myo": {"holes_filled": 31, "islands_dropped": 2, "island_voxels": 9}},
              "walls_filled": [{"structures": ["myo", "rv"], "voxels": 282}], "contacts_cut": [], "handles": []}
    assert _summary(record) == ("Euler characteristic before -12; labels cleaned: ['myo 31 hole vox filled, "
                                "2 islands (9 vox) dropped']; walls filled: ['myo-rv 282 vox']; contacts cut: none; "
                                "handles: none")


def _ventricle(shape, voxel_mm, centre_mm):
    """An LV pool (ellipsoid 20 x 20 x 35 mm) in a 6 mm myocardium, voxel_mm apart, its centre at centre_mm."""
    grid = np.stack(np.meshgrid(*[np.arange(n) * d for n, d in zip(shape, voxel_mm)], indexing="ij"), axis=-1)
    r = np.linalg.norm((grid - centre_mm) / (20.0, 20.0, 35.0), axis=-1)
    labels = np.where(r <= 1.0, STRUCTURES["lv"], np.where(r <= 1.3, STRUCTURES["myo"], 0)).astype(np.uint8)
    return labels, np.diag([*voxel_mm, 1.0])


def test_a_map_whose_border_cuts_a_chamber_off_fails_naming_the_structures_and_the_face():
    """A CT's field of view cutting the ventricles' lowest 12 mm was meshed into a heart closed flat on the border
    (402 ml against 421), accepted into the shape model. A whole map passes; a thick-slice stack's slice ends cut
    the shape by design (its base, flat_ends); max_border_mm2 = inf accepts the cut map."""
    whole, affine = _ventricle((70, 70, 110), (1.0, 1.0, 1.0), (35.0, 35.0, 55.0))
    labels_to_surface(whole, affine, ["lv", "myo"], MeshingParams(spacing_mm=1.5))
    cut = whole[:, :, 28:]  # the lowest 28 mm of a 45.5 mm half-height: myo and LV pool on the first z face
    with pytest.raises(MeshError, match=r"the label map's border cuts the heart: \{'lv': \{'axis 2 first': \d+.*"
                                        r"'myo': \{'axis 2 first': \d+"):
        labels_to_surface(cut, affine, ["lv", "myo"], MeshingParams(spacing_mm=1.5))
    accepted = labels_to_surface(cut, affine, ["lv", "myo"], MeshingParams(spacing_mm=1.5, max_border_mm2=np.inf))
    assert trimesh.Trimesh(accepted.verts, accepted.faces).is_watertight
    stack, stack_affine = _ventricle((70, 70, 14), (1.5, 1.5, 8.0), (52.5, 52.5, 55.0))
    labels_to_surface(stack[:, :, 3:], stack_affine, ["lv", "myo"], MeshingParams())  # its base cut by the stack
    with pytest.raises(MeshError, match=r"'axis 0 last'"):  # but not across a slice
        labels_to_surface(stack[:40], stack_affine, ["lv", "myo"], MeshingParams())


def test_empty_mask_is_named_input_error():
    labels = np.zeros((10, 10, 10), np.uint8)
    labels[2:5, 2:5, 2:5] = STRUCTURES["la"]
    with pytest.raises(InputError, match=r"case7: none of the structures \['lv', 'rv'\] present \(found: \['la'\]\)"):
        labels_to_surface(labels, np.eye(4), ["lv", "rv"], MeshingParams(), name="case7")


@pytest.mark.parametrize("thin_axis", [0, 1, 2])
def test_a_single_slice_map_is_named_input_error(thin_axis):
    """A long-axis cine view (M&Ms-2's 4-chamber maps are 256 x 256 x 1) has no solid to mesh: the error names the
    file and the axis, not a mask that vanished in the smoothing. Two slices are a solid and mesh."""
    shape = [40, 40, 40]
    shape[thin_axis] = 1
    labels = np.zeros(shape, np.uint8)
    inner = [slice(5, 35)] * 3
    inner[thin_axis] = slice(0, 1)
    labels[tuple(inner)] = STRUCTURES["lv"]
    with pytest.raises(InputError, match=rf"la_ed.nii.gz: the structures \['lv'\] are one voxel thick along voxel axis {thin_axis}"):
        labels_to_surface(labels, np.diag([1.7, 1.7, 1.7, 1.0]), ["lv"], MeshingParams(), name="la_ed.nii.gz")
    two = np.concatenate([labels, labels], axis=thin_axis)
    # every voxel of it on the box's border: the border check let off
    surface = labels_to_surface(two, np.diag([8.0, 8.0, 8.0, 1.0]), ["lv"], MeshingParams(max_border_mm2=np.inf),
                                name="two")
    assert is_closed_genus0(surface.verts, surface.faces)[0]


def test_vertex_labels_follow_nearest_structure():
    mask, affine = ball_volume((50, 50, 50), (1, 1, 1), 18)
    labels = mask.astype(np.uint8) * STRUCTURES["lv"]
    z = (np.arange(50) - 24.5)[None, None, :]
    labels[mask & (z > 0)] = STRUCTURES["la"]
    s = labels_to_surface(labels, affine, ["lv", "la"], MeshingParams())
    top, bottom = s.verts[:, 2] > 2, s.verts[:, 2] < -2
    assert np.all(s.labels[top] == STRUCTURES["la"]) and np.all(s.labels[bottom] == STRUCTURES["lv"])


@settings(max_examples=8, deadline=None)
@given(
    axes=st.tuples(*[st.floats(8, 25)] * 3),
    voxel=st.tuples(st.floats(0.8, 2.0), st.floats(0.8, 2.0), st.floats(0.8, 6.0)),
    spacing=st.sampled_from([1.0, 1.5]),
)
@example(axes=(8.0, 8.0, 8.0), voxel=(1.0, 1.0, 5.0), spacing=1.5)  # three slices through a sphere
@example(axes=(8.0, 8.0, 8.0), voxel=(1.0, 1.0, 1.0), spacing=1.5)  # the smoothing's shrinkage at its largest
def test_ellipsoids_any_voxel_size_are_closed_genus0(axes, voxel, spacing):
    shape = np.ceil(70 / np.asarray(voxel)).astype(int)
    mask, affine = ball_volume(shape, voxel, None, axes_mm=axes)
    params = MeshingParams(spacing_mm=spacing)
    _, m = mesh_of(mask, affine, params)
    assert m.is_watertight and m.euler_number == 2
    # Thick slices lose the caps: half a slice at each pole along z, two caps of height
    # h = voxel_z / 2 hold (h/c)^2 (3 - h/c) / 2 of the volume (exact for any ellipsoid, since
    # scaling z scales both). The Gaussian smoothing of the distance moves a sphere's surface in
    # by sigma^2 / R, a volume fraction of 3 sigma^2 / R^2 (4.7 % at R = 8 mm, sigma = 1 mm: an
    # 8 mm ball at 1.5 mm spacing lost 5.6 %); sigma^2 (1/a^2 + 1/b^2 + 1/c^2) for the axes. Plus
    # 5 % for everything else: a bound that still catches gross errors.
    x = voxel[2] / 2 / axes[2]
    smoothing = params.sigma_mm**2 * sum(1 / a**2 for a in axes)
    assert abs(m.volume / (4 / 3 * np.pi * np.prod(axes)) - 1) < 0.05 + x**2 * (3 - x) / 2 + smoothing


# --- vessel trimming -----------------------------------------------------------------------------


def canonical_whole_heart(seed: int, voxel_mm: float = 2.0):
    """A whole-heart phantom's label map in canonical ids, its affine and its parameters."""
    from meshsar_builder.dataset.sources import MMWHS_TABLE
    from meshsar_builder.geometry import phantom_heart

    params = phantom_heart.sample_whole_heart_params(np.random.default_rng(seed))
    codes, affine = phantom_heart.whole_heart_labels(params, (voxel_mm,) * 3)
    lut = np.zeros(codes.max() + 1, np.uint8)
    for code, name in MMWHS_TABLE.items():
        lut[code] = STRUCTURES[name]
    return lut[codes], affine, params


def world_of(mask, affine):
    return np.argwhere(mask) @ affine[:3, :3].T + affine[:3, 3]


@pytest.mark.parametrize("seed", [0, 5])
def test_vessels_are_cut_at_their_length_from_the_valve(seed):
    labels, affine, p = canonical_whole_heart(seed)
    trimmed = trim_vessels(labels, affine, {"aorta": 30.0, "pa": 25.0})
    # the phantom's own centreline directions: the ascending aorta and the pulmonary trunk are straight
    tilt_r, tilt_a = np.radians([p["ascending_tilt_right_deg"], p["ascending_tilt_anterior_deg"]])
    ascending = np.array([np.tan(tilt_r), np.tan(tilt_a), 1.0]) / np.linalg.norm([np.tan(tilt_r), np.tan(tilt_a), 1.0])
    pitch, yaw = np.radians([p["pa_pitch_deg"], p["pa_yaw_deg"]])
    trunk = np.array([-np.sin(yaw) * np.sin(pitch), -np.cos(yaw) * np.sin(pitch), np.cos(pitch)])
    for vessel, chamber, axis, length in (("aorta", "lv", ascending, 30.0), ("pa", "rv", trunk, 25.0)):
        kept = trimmed == STRUCTURES[vessel]
        valve = kept & ndimage.binary_dilation(trimmed == STRUCTURES[chamber])
        reach = (world_of(kept, affine) @ axis).max() - world_of(valve, affine).mean(axis=0) @ axis
        assert length - 4.0 <= reach <= length + 4.0, (vessel, reach)
        assert kept.sum() < (labels == STRUCTURES[vessel]).sum()
        assert ndimage.label(kept)[1] == 1
    for name in ("lv", "myo", "rv", "la", "ra"):
        assert np.array_equal(trimmed == STRUCTURES[name], labels == STRUCTURES[name])
    surf = labels_to_surface(labels, affine, list(STRUCTURES),
                             MeshingParams(spacing_mm=2.0, sigma_mm=1.5, vessel_length_mm={"aorta": 30.0, "pa": 25.0}))
    mesh = trimesh.Trimesh(surf.verts, surf.faces, process=False)
    assert mesh.is_watertight and mesh.euler_number == 2 and surf.repair == {}


def test_trimming_removes_a_vessel_that_comes_back_to_a_chamber():
    """An aorta that arches over and comes down onto the LA (which touches the LV) closes a
    handle; cut at 30 mm it leaves one genus-0 solid, the atrium untouched."""
    axes = [np.arange(-30.0, 71.0), np.arange(-25.0, 26.0), np.arange(-30.0, 95.0)]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    affine = np.diag([1.0, 1.0, 1.0, 1.0])
    affine[:3, 3] = [a[0] for a in axes]
    arch = np.sqrt((np.sqrt((x - 20) ** 2 + (z - 60) ** 2) - 20) ** 2 + y**2)
    ring = np.sqrt(x**2 + y**2), np.sqrt((x - 40) ** 2 + y**2)
    tube = np.where(z >= 60, arch, np.minimum(np.where(z >= 0, ring[0], np.inf), np.where(z >= 0, ring[1], np.inf))) <= 7
    labels = np.zeros(x.shape, np.uint8)
    labels[tube] = STRUCTURES["aorta"]
    labels[(x - 40) ** 2 + y**2 + (z + 5) ** 2 <= 22**2] = STRUCTURES["la"]
    labels[x**2 + y**2 + z**2 <= 20**2] = STRUCTURES["lv"]
    assert euler_number(labels > 0, connectivity=3) == 0  # one handle
    trimmed = trim_vessels(labels, affine, {"aorta": 30.0})
    aorta = world_of(trimmed == STRUCTURES["aorta"], affine)
    assert 47.0 <= aorta[:, 2].max() <= 52.0 and aorta[:, 0].max() < 8.0  # the ascending part only
    assert np.array_equal(trimmed == STRUCTURES["la"], labels == STRUCTURES["la"])
    assert euler_number(trimmed > 0, connectivity=3) == 1
    surf = labels_to_surface(labels, affine, ["lv", "la", "aorta"], MeshingParams(vessel_length_mm={"aorta": 30.0}))
    mesh = trimesh.Trimesh(surf.verts, surf.faces, process=False)
    assert mesh.is_watertight and mesh.euler_number == 2 and surf.repair == {}


def test_a_vessel_without_its_valve_is_named():
    labels = np.zeros((20, 20, 20), np.uint8)
    labels[2:8, 2:8, 2:8] = STRUCTURES["pa"]
    labels[12:18, 12:18, 12:18] = STRUCTURES["rv"]
    with pytest.raises(MeshError, match="case.nii: pa touches no rv"):
        trim_vessels(labels, np.eye(4), {"pa": 25.0}, name="case.nii")


# --- thick-slice short-axis stacks ---------------------------------------------------------------


def half_spheroid_sdf(p, r=25.0, length=70.0):
    """A bound on the distance to an LV-like half prolate spheroid (base plane z = 0, apex at z = length)."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return np.maximum((np.sqrt((x / r) ** 2 + (y / r) ** 2 + (z / length) ** 2) - 1) * r, -z)


def thick_slice_stack(slice_mm, offset_mm=0.0):
    """The half-spheroid sliced as a short-axis stack (1.5 mm in plane, the base on a slice boundary, as a stack
    planned at the valve plane is; offset_mm moves it in plane): mask (X, Y, Z) bool and affine (4, 4)."""
    voxel = np.array([1.5, 1.5, slice_mm])
    lo = np.array([-44.3 + offset_mm, -45.1 + offset_mm, slice_mm / 2 - slice_mm * np.ceil(45 / slice_mm)])
    axes = [lo[i] + voxel[i] * np.arange(int(np.ceil(n / voxel[i])) + 2) for i, n in enumerate((90, 90, 135))]
    affine = np.diag([*voxel, 1.0])
    affine[:3, 3] = lo
    return half_spheroid_sdf(np.stack(np.meshgrid(*axes, indexing="ij"), -1)) <= 0, affine


def volume_and_distance(mask, affine, params):
    """(relative volume error, mean distance (mm) to the true surface, reach (mm) past the base plane) of the
    half-spheroid's mesh."""
    _, m = mesh_of(mask, affine, params)
    assert m.is_watertight and m.euler_number == 2
    points, _ = trimesh.sample.sample_surface(m, 5000, seed=0)
    volume = m.volume / (2 / 3 * np.pi * 25**2 * 70) - 1
    return volume, np.abs(half_spheroid_sdf(points)).mean(), -m.vertices[:, 2].min()


@pytest.mark.parametrize("slice_mm", [6.0, 8.0, 10.0])
@pytest.mark.parametrize("offset_mm", [0.0, 0.5])
def test_thick_slices_keep_the_volume_and_cut_the_base_flat(slice_mm, offset_mm):
    """An LV-like shape sliced as a short-axis stack: with flat_ends (the default), its volume within 2 % of the
    analytic one, both the volume and the mean distance to the true surface better than with the base rounded as
    the interpolation alone rounds it, and the surface within 1 mm past the base plane (measured: -0.6 / -0.6 /
    -0.2 %, 0.17 / 0.20 / 0.24 mm and 0.45 / 0.69 / 0.88 mm past, against -1.1 / -1.6 / -2.1 % and 0.18 / 0.24 /
    0.30 mm rounded at 6 / 8 / 10 mm; linear resampling lost 1.9-4.0 %; with only the first slice beyond the
    base flattened, 0.85 / 1.64 / 2.40 mm past it)."""
    mask, affine = thick_slice_stack(slice_mm, offset_mm)
    volume, distance, reach = volume_and_distance(mask, affine, MeshingParams())
    rounded_volume, rounded_distance, _ = volume_and_distance(mask, affine, MeshingParams(flat_ends=False))
    assert abs(volume) < 0.02 and abs(volume) < abs(rounded_volume) < 0.025
    assert distance < rounded_distance < 0.3
    assert reach < 1.0, reach


@pytest.mark.parametrize("voxel", [(1.5, 1.5, 8.0), (1.5, 1.5, 10.0)])
def test_a_thick_slice_stack_that_closes_keeps_its_rounded_ends(voxel):
    """A sphere closes at both ends of the stack (its last slices narrower than the ones before): with flat_ends it
    meshes to the same bytes as without, where a flat cap would make its poles discs."""
    mask, affine = ball_volume(np.ceil(90 / np.asarray(voxel)).astype(int), voxel, 30.0, centre_mm=(0.0, 0.0, 2.0))
    surface, _ = mesh_of(mask, affine)
    rounded, _ = mesh_of(mask, affine, MeshingParams(flat_ends=False))
    assert np.array_equal(surface.verts, rounded.verts) and np.array_equal(surface.faces, rounded.faces)


def test_a_short_axis_maps_apical_lv_gap_is_meshed_as_myocardium_and_recorded():
    """A ball of myocardium round an LV cavity, cut flat at the top (the basal cut shows the LV)
    with the wall missing at the bottom (an apical slice labelled blood pool only): the surface
    shows LV at the base only, and the meshes sidecar's record lists the patch relabelled."""
    mask, affine = ball_volume((50, 50, 50), (1, 1, 1), 20)
    cavity, _ = ball_volume((50, 50, 50), (1, 1, 1), 14)
    z = (np.arange(50) - 24.5)[None, None, :]
    x = (np.arange(50) - 24.5)[:, None, None]
    y = (np.arange(50) - 24.5)[None, :, None]
    labels = np.where(mask, STRUCTURES["myo"], 0).astype(np.uint8)
    labels[cavity] = STRUCTURES["lv"]
    labels[mask & (z > 12)] = 0  # the basal cut
    labels[mask & (z < -10) & (x**2 + y**2 < 25)] = STRUCTURES["lv"]  # the apical gap through the wall
    surface = labels_to_surface(labels, affine, ["lv", "myo"], MeshingParams())
    lv = surface.labels == STRUCTURES["lv"]
    assert lv.any() and (surface.verts[lv, 2] > 5).all()  # at the base only
    assert (surface.labels[surface.verts[:, 2] < -17] == STRUCTURES["myo"]).all()
    [patch] = surface.repair["lv_patches_relabelled"]
    assert patch["vertices"] > 0 and 10 < patch["area_mm2"] < 400
    # A whole heart's labels are left as drawn.
    labels[mask & (y > 12)] = STRUCTURES["la"]
    whole = labels_to_surface(labels, affine, ["lv", "myo", "la"], MeshingParams())
    assert "lv_patches_relabelled" not in whole.repair and (whole.labels[whole.verts[:, 2] < -17] == STRUCTURES["lv"]).any()


@settings(max_examples=40, deadline=None)
@given(st.tuples(*[st.integers(2, 14)] * 3), st.tuples(*[st.floats(0.1, 2.5)] * 3), st.integers(0, 2**32 - 1))
def test_separable_cubic_resampling_is_scipys_map_coordinates(shape, steps, seed):
    """The meshing's resampling, one axis at a time, against scipy's cubic B-spline at every point of the grid
    (mode "nearest"), on random volumes, anisotropic steps finer and coarser than a voxel."""
    values = np.random.default_rng(seed).standard_normal(shape) * 20
    axes = [np.arange(0, n - 1 + 1e-9, step) for n, step in zip(shape, steps)]
    reference = ndimage.map_coordinates(values, np.meshgrid(*axes, indexing="ij"), order=3, mode="nearest")
    resampled = resample_cubic(values, axes)
    assert resampled.shape == reference.shape
    np.testing.assert_allclose(resampled, reference, rtol=0, atol=1e-11)


def _pools(gap_voxels: int, island: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """An LV pool (radius 10 mm) and a smaller RV pool (9 mm) along x, `gap_voxels` apart (1 mm voxels), and
    optionally a 2-voxel RV island far off."""
    labels = np.zeros((70, 40, 40), np.uint8)
    x, y, z = np.ogrid[:70, :40, :40]
    labels[(x - 15) ** 2 + (y - 20) ** 2 + (z - 20) ** 2 <= 100] = STRUCTURES["lv"]
    labels[(x - 35 - gap_voxels) ** 2 + (y - 20) ** 2 + (z - 20) ** 2 <= 81] = STRUCTURES["rv"]
    if island:
        labels[66:68, 5, 5] = STRUCTURES["rv"]
    return labels, np.diag([1.0, 1.0, 1.0, 1.0])


def test_a_structure_apart_from_the_rest_is_refused_naming_it_and_an_island_is_recorded():
    """contour keeps one piece: a structure lying apart (pools without the wall between them) would vanish from
    the surface, so it is an error with its volume; a touching pair meshes whole, and a small island of a
    structure is left out and recorded."""
    labels, affine = _pools(gap_voxels=4)
    with pytest.raises(InputError, match=r"2 separate pieces.*apart from it lie rv \(3\.\d of 3\.\d ml\)"):
        labels_to_surface(labels, affine, ["lv", "rv"], MeshingParams(), name="pools.nii.gz")
    joined = labels.copy()
    bar = joined[24:41, 17:24, 17:24]  # a view: the wall between the pools, where they leave background
    bar[bar == 0] = STRUCTURES["myo"]
    surface = labels_to_surface(joined, affine, ["lv", "myo", "rv"], MeshingParams())
    volume = trimesh.Trimesh(surface.verts, surface.faces).volume
    assert volume > 7000 and "pieces_apart_ml" not in surface.repair  # both pools (4.2 and 3.1 ml) and the bar
    touching, _ = _pools(gap_voxels=0, island=True)
    surface = labels_to_surface(touching, affine, ["lv", "rv"], MeshingParams())
    assert surface.repair["pieces_apart_ml"] == {"rv": 0.002}
    assert {STRUCTURES["lv"], STRUCTURES["rv"]} <= set(np.unique(surface.labels))


def test_a_structure_missing_from_the_map_is_refused_naming_it():
    labels, affine = _pools(gap_voxels=0)
    with pytest.raises(InputError, match=r"pools.nii.gz: the structures \['myo'\] are missing.*found: \['lv', 'rv'\]"):
        labels_to_surface(labels, affine, ["lv", "myo", "rv"], MeshingParams(), name="pools.nii.gz")


def test_long_axis_landmarks_find_the_apex_whichever_way_the_slices_run():
    """A half prolate spheroid LV (not the phantom; base plane at z = 40 mm, epicardial apex at z = -30) in 5 mm
    slices: its apex and base come out the same for either sign of the slice normal and either slice order."""
    i, j, k = np.meshgrid(np.arange(30), np.arange(30), np.arange(20), indexing="ij")
    affine = np.diag([2.0, 2.0, 5.0, 1.0])
    affine[:3, 3] = [-29.0, -29.0, -50.0]
    x, y, z = (index * step + origin for index, step, origin in zip((i, j, k), (2.0, 2.0, 5.0), affine[:3, 3]))
    outer = (x**2 + y**2) / 20**2 + (z - 40) ** 2 / 70**2 <= 1
    inner = (x**2 + y**2) / 14**2 + (z - 40) ** 2 / 62**2 <= 1
    labels = np.where(inner, STRUCTURES["lv"], np.where(outer, STRUCTURES["myo"], 0)).astype(np.uint8)
    labels[z > 40] = 0
    flipped = np.array(affine)
    flipped[:3, 2] = -affine[:3, 2]
    flipped[:3, 3] = affine[:3, 3] + 19 * affine[:3, 2]  # the last slice first: the same world
    for lab, aff in ((labels, affine), (labels[:, :, ::-1], flipped)):
        for sign in (1, -1):
            apex, base = long_axis_landmarks(lab, aff, sign * aff[:3, 2])
            assert np.allclose(apex[:2], 0, atol=1.0) and apex[2] == pytest.approx(-30, abs=5)
            assert base == pytest.approx(-40, abs=0.1)  # the basal slice at z = 40, along the axis toward the apex
