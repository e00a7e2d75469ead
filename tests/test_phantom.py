"""The built-in phantoms: reproducible files, heart-like anatomy, one genus-0 solid, a realistic beat."""

from __future__ import annotations

import re

import nibabel as nib
import numpy as np
import pytest
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import ndimage
from skimage.measure import euler_number, marching_cubes

from meshsar_builder.dataset.sources import MMWHS_TABLE
from meshsar_builder.geometry import phantom_beating, phantom_heart
from meshsar_builder.geometry.meshing import long_axis_landmarks
from meshsar_builder.geometry.structures import STRUCTURES

MMWHS_CODES = (205, 420, 500, 550, 600, 820, 850)
COARSE = (2.0, 2.0, 2.0)  # whole heart at 2 mm: 8x fewer voxels, same anatomy


def rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed)


def world_points(ijk: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Voxel indices (N, 3) -> RAS mm (N, 3)."""
    return ijk @ affine[:3, :3].T + affine[:3, 3]


def centroid(labels: np.ndarray, affine: np.ndarray, *codes: int) -> np.ndarray:
    return world_points(np.argwhere(np.isin(labels, codes)), affine).mean(axis=0)


def surface_topology(mask: np.ndarray) -> tuple[bool, int]:
    """Marching cubes of a voxel mask (lightly smoothed, as the meshing stage does): whether its
    largest surface component is watertight, and that component's Euler characteristic."""
    field = ndimage.gaussian_filter(np.pad(mask, 2).astype(np.float32), 1.0)
    verts, faces, _, _ = marching_cubes(field, 0.5)
    largest = max(trimesh.Trimesh(verts, faces).split(only_watertight=False), key=lambda m: len(m.faces))
    return largest.is_watertight, largest.euler_number


@pytest.fixture(scope="module")
def coarse_hearts():
    """Whole hearts of a few seeds at 2 mm: (labels, affine) by seed."""
    return {seed: phantom_heart.whole_heart_labels(phantom_heart.sample_whole_heart_params(rng(seed)), COARSE) for seed in range(4)}


# --- whole heart -------------------------------------------------------------------------------


def test_mmwhs_file_is_reproducible_and_readable(tmp_path):
    a = phantom_heart.write_mmwhs_subject(tmp_path / "a", "ct_train_1001", rng(7), voxel_mm=COARSE)
    b = phantom_heart.write_mmwhs_subject(tmp_path / "b", "ct_train_1001", rng(7), voxel_mm=COARSE)
    c = phantom_heart.write_mmwhs_subject(tmp_path / "c", "ct_train_1001", rng(8), voxel_mm=COARSE)
    assert a.name == "ct_train_1001_label.nii.gz" and a.parent == tmp_path / "a"
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()
    assert sorted(p.name for p in a.parent.iterdir()) == [a.name]  # no temporary left behind
    image = nib.load(a)
    labels = np.asarray(image.dataobj)
    assert labels.dtype == np.uint16
    assert set(np.unique(labels)) == {0, *MMWHS_CODES}
    np.testing.assert_allclose(image.header.get_zooms(), COARSE)
    # Canonical reorientation (as the loaders do) keeps every structure's world position.
    canonical = nib.as_closest_canonical(image)
    moved = np.asarray(canonical.dataobj)
    for code in MMWHS_CODES:
        np.testing.assert_allclose(centroid(labels, image.affine, code), centroid(moved, canonical.affine, code), atol=1e-6)


@pytest.mark.parametrize("seed", range(4))
def test_whole_heart_anatomy(coarse_hearts, seed):
    labels, affine = coarse_hearts[seed]
    assert labels.dtype == np.uint16 and affine.shape == (4, 4)
    assert set(np.unique(labels)) == {0, *MMWHS_CODES}
    lv = centroid(labels, affine, 205, 500)
    rv = centroid(labels, affine, 600)
    la, ra = centroid(labels, affine, 420), centroid(labels, affine, 550)
    aorta, pa = centroid(labels, affine, 820), centroid(labels, affine, 850)
    x, y, z = 0, 1, 2
    assert lv[x] < rv[x], "LV left of RV"
    assert rv[y] > lv[y], "RV anterior of LV"
    for atrium in (la, ra):
        assert atrium[z] > lv[z] and atrium[z] > rv[z], "atria superior to the ventricles"
        assert atrium[y] < rv[y], "atria posterior to the RV"
    assert la[y] < lv[y], "LA posterior to the LV"
    assert la[x] < ra[x], "LA left of RA"
    assert pa[y] > aorta[y], "PA anterior to the aorta"
    assert aorta[z] > lv[z] + 30, "aorta above the LV"
    # Apex: the LV voxel farthest from the mitral plane (LV voxels touching the LA).
    lv_mask = np.isin(labels, (205, 500))
    mitral = lv_mask & ndimage.binary_dilation(labels == 420)
    base = world_points(np.argwhere(mitral), affine).mean(axis=0)
    lv_points = world_points(np.argwhere(lv_mask), affine)
    apex = lv_points[np.argmax(np.linalg.norm(lv_points - base, axis=1))]
    direction = (apex - base) / np.linalg.norm(apex - base)
    assert direction[x] < -0.2 and direction[y] > 0.2 and direction[z] < -0.2, direction
    assert 70 < np.linalg.norm(apex - base) < 115  # long axis in mm


@pytest.mark.parametrize("seed", range(4))
def test_whole_heart_myocardium_wraps_the_cavity(coarse_hearts, seed):
    labels, _ = coarse_hearts[seed]
    # The blood pool touches the myocardium, LA (mitral), aorta (outflow) and, at the open base,
    # the outside; never the right heart.
    neighbours = labels[ndimage.binary_dilation(labels == 500) & (labels != 500)]
    assert {205, 420} <= set(np.unique(neighbours)) <= {0, 205, 420, 820}
    # The wall is ~8-12 mm: the myocardium is far thinner than the cavity is wide.
    thickness = ndimage.distance_transform_edt(labels == 205)[labels == 205].max() * 2 * COARSE[0]
    assert 6 <= thickness <= 20


@pytest.mark.parametrize("seed", range(4))
def test_whole_heart_union_is_one_genus_zero_solid(coarse_hearts, seed):
    mask = coarse_hearts[seed][0] > 0
    assert ndimage.label(mask)[1] == 1
    assert euler_number(mask, connectivity=1) == 1 and euler_number(mask, connectivity=3) == 1
    assert surface_topology(mask) == (True, 2)


@pytest.mark.slow
@settings(deadline=None, max_examples=12)
@given(seed=st.integers(0, 2**32 - 1))
# pulmonary branches that leave the fork nearer the body than the vessel gap and run on into it
@example(seed=988)
@example(seed=60244540)
def test_whole_heart_union_genus_zero_at_1mm(seed):
    labels, _ = phantom_heart.whole_heart_labels(phantom_heart.sample_whole_heart_params(rng(seed)))
    mask = labels > 0
    assert set(np.unique(labels)) == {0, *MMWHS_CODES}
    assert ndimage.label(mask)[1] == 1
    assert euler_number(mask, connectivity=1) == 1 and euler_number(mask, connectivity=3) == 1
    assert surface_topology(mask) == (True, 2)


def test_whole_heart_volumes_stay_in_the_stated_ranges():
    """Labelled volumes (voxel counts at 2 mm, within ~1 % of 1 mm) of 20 seeds, RA 35-70 ml included."""
    volumes = {name: [] for name in phantom_heart.WHOLE_HEART_VOLUMES_ML}
    for seed in range(20):
        labels, affine = phantom_heart.whole_heart_labels(phantom_heart.sample_whole_heart_params(rng(100 + seed)), COARSE)
        voxel_ml = abs(np.linalg.det(affine[:3, :3])) / 1000
        for code, name in MMWHS_TABLE.items():
            if code != 421:
                volumes[name].append(np.count_nonzero(labels == code) * voxel_ml)
    assert phantom_heart.WHOLE_HEART_VOLUMES_ML["ra"] == (35.0, 70.0)
    for name, (low, high) in phantom_heart.WHOLE_HEART_VOLUMES_ML.items():
        assert low <= min(volumes[name]) and max(volumes[name]) <= high, (name, min(volumes[name]), max(volumes[name]))
        assert np.ptp(volumes[name]) > 0.15 * np.mean(volumes[name]), f"{name} volume varies among subjects"


def test_whole_heart_parameters_vary_within_documented_ranges():
    a, b = phantom_heart.sample_whole_heart_params(rng(0)), phantom_heart.sample_whole_heart_params(rng(1))
    assert a == phantom_heart.sample_whole_heart_params(rng(0))
    assert a.keys() == b.keys() == phantom_heart.WHOLE_HEART_RANGES.keys()
    assert sum(a[k] != b[k] for k in a) >= 15
    for params in (a, b):
        for name, (low, high) in phantom_heart.WHOLE_HEART_RANGES.items():
            assert low <= params[name] <= high


# --- biventricular -----------------------------------------------------------------------------


@settings(deadline=None, max_examples=5)
@given(seed=st.integers(0, 2**32 - 1))
def test_biventricular_beat_is_realistic(seed):
    params = phantom_beating.sample_biventricular_params(rng(seed))
    frames, affines, info = phantom_beating.biventricular_frames(params, n_frames=20)
    assert len(frames) == 20 and all(f.dtype == np.uint8 and f.shape == frames[0].shape for f in frames)
    assert affines.shape == (20, 4, 4) and np.allclose(affines[:, :3, :3], affines[0, :3, :3])
    np.testing.assert_allclose(np.linalg.norm(affines[0, :3, :3], axis=0), (1.5, 1.5, 8.0))
    voxel_ml = abs(np.linalg.det(affines[0, :3, :3])) / 1000
    lv = np.array([np.count_nonzero(f == 3) for f in frames]) * voxel_ml
    rv = np.array([np.count_nonzero(f == 1) for f in frames]) * voxel_ml
    myo = np.array([np.count_nonzero(f == 2) for f in frames]) * voxel_ml
    assert all(set(np.unique(f)) == {0, 1, 2, 3} for f in frames)
    assert np.argmax(lv) == 0 and info["ed_frame"] == 1
    es = int(np.argmin(lv))
    assert info["es_frame"] == es + 1
    assert 0.25 <= es / 20 <= 0.45
    ef = 1 - lv[es] / lv[0]
    assert 0.55 <= ef <= 0.70 and abs(ef - params["lv_ef"]) < 0.03
    assert info["ef"] == pytest.approx(ef)
    np.testing.assert_allclose(info["lv_volume_ml"], lv)
    assert 120 <= lv[0] <= 160 and 130 <= rv[0] <= 190, "adult end-diastolic volumes"
    assert np.ptp(myo) / myo.mean() < 0.05, "myocardial volume conserved"
    # Filling: rapid early filling, then a slow diastasis, then the atrial kick before ED.
    assert lv[es + 4] - lv[es] > lv[15] - lv[es + 4] > 0 and lv[19] > lv[16]
    rv_ef = 1 - rv.min() / rv[0]
    assert 0.43 <= rv_ef <= 0.72
    assert (rv[0] - rv.min()) / (lv[0] - lv.min()) == pytest.approx(1.0, abs=0.1), "RV and LV stroke volumes match"
    # The wall thickens in systole: myocardial voxels per LV voxel-ring grow from ED to ES.
    mid = frames[0].shape[2] // 3
    wall = [np.count_nonzero(frames[i][:, :, mid] == 2) / np.sqrt(np.count_nonzero(frames[i][:, :, mid] == 3)) for i in (0, es)]
    assert wall[1] > wall[0]


def rv_angle_deg(labels: np.ndarray, k: int) -> float:
    """Angle of the RV centroid about the LV cavity's centre in slice k, from the first voxel
    axis toward the second (counter-clockwise seen from the apex)."""
    rv, lv = np.argwhere(labels[:, :, k] == 1).mean(axis=0), np.argwhere(labels[:, :, k] == 3).mean(axis=0)
    return float(np.degrees(np.arctan2(rv[1] - lv[1], rv[0] - lv[0])))


def test_beat_keeps_the_apex_still_lowers_the_base_and_twists():
    """At 2 mm slices (motion measured to the voxel): apex within 5 mm, AV plane down 12-15 mm
    at end-systole, base and apex turning opposite ways."""
    params = phantom_beating.sample_biventricular_params(rng(2))
    frames, affines, info = phantom_beating.biventricular_frames(params, n_frames=10, voxel_mm=(2.0, 2.0, 2.0))
    es = info["es_frame"] - 1
    # ACDC codes (1 RV, 2 myo, 3 LV) to canonical ids, as the loader maps them
    canonical = np.array([0, STRUCTURES["rv"], STRUCTURES["myo"], STRUCTURES["lv"]], np.uint8)
    landmarks = [long_axis_landmarks(canonical[f], a, a[:3, 2]) for f, a in zip(frames, affines)]
    apex = np.array([a for a, _ in landmarks])
    base = np.array([b for _, b in landmarks])
    assert np.linalg.norm(apex - apex[0], axis=1).max() < 5.0
    assert 12.0 <= base[es] - base[0] <= 15.0
    assert base[es] - base[0] == pytest.approx(info["base_descent_mm"][es], abs=1.0)
    assert np.argmax(base) == es
    # Twist: the RV crescent (symmetric at ED) turns clockwise near the base, counter-clockwise
    # toward the apex, by angles linear in depth (zero a third of the way down the epicardium).
    basal, apical = 2, int(0.6 * np.count_nonzero(np.isin(frames[es], (2, 3)).any(axis=(0, 1))))
    assert abs(rv_angle_deg(frames[0], basal)) < 0.5 and abs(rv_angle_deg(frames[0], apical)) < 0.5
    turn = rv_angle_deg(frames[es], apical) - rv_angle_deg(frames[es], basal)
    assert rv_angle_deg(frames[es], basal) < -1.0 and 0.2 * info["twist_deg"][es] < turn < info["twist_deg"][es]


def test_biventricular_rv_is_a_crescent_beside_the_lv():
    frames, affine, _ = phantom_beating.biventricular_frames(phantom_beating.sample_biventricular_params(rng(3)))
    labels = frames[0]
    mid = labels[:, :, labels.shape[2] // 3]
    rv = np.argwhere(mid == 1)
    lv_centre = np.argwhere(mid == 3).mean(axis=0)
    # A crescent: the RV's centroid lies outside the RV itself, and it touches the myocardium.
    rv_centre = np.round(rv.mean(axis=0)).astype(int)
    assert mid[tuple(rv_centre)] != 1
    assert np.any(mid[ndimage.binary_dilation(mid == 1)] == 2)
    assert np.linalg.norm(rv.mean(axis=0) - lv_centre) > 10
    assert ndimage.label(mid == 1)[1] == 1


def test_acdc_subject_layout_and_reproducibility(tmp_path):
    subject = phantom_beating.write_acdc_subject(tmp_path / "a", "patient001", rng(5), n_frames=12)
    again = phantom_beating.write_acdc_subject(tmp_path / "b", "patient001", rng(5), n_frames=12)
    other = phantom_beating.write_acdc_subject(tmp_path / "c", "patient001", rng(6), n_frames=12)
    assert subject == tmp_path / "a" / "patient001"
    names = sorted(p.name for p in subject.iterdir())
    assert names == ["Info.cfg"] + [f"patient001_frame{i:02d}_gt.nii.gz" for i in range(1, 13)]
    for name in names:
        assert (subject / name).read_bytes() == (again / name).read_bytes()
    assert (subject / names[1]).read_bytes() != (other / names[1]).read_bytes()

    cfg = dict(re.fullmatch(r"(\w+): (.+)", line).groups() for line in (subject / "Info.cfg").read_text().splitlines())
    assert list(cfg) == ["ED", "ES", "Group", "Height", "NbFrame", "Weight"]
    assert cfg["Group"] == "NOR" and int(cfg["NbFrame"]) == 12 and int(cfg["ED"]) == 1
    assert 150 <= float(cfg["Height"]) <= 195 and 45 <= float(cfg["Weight"]) <= 100

    images = [nib.load(subject / f"patient001_frame{i:02d}_gt.nii.gz") for i in range(1, 13)]
    np.testing.assert_allclose(images[0].header.get_zooms(), (1.5, 1.5, 8.0))
    es = int(cfg["ES"]) - 1  # the stack follows the base plane toward the apex
    descent = (images[es].affine[:3, 3] - images[0].affine[:3, 3]) @ images[0].affine[:3, 2] / 8.0
    assert 12.0 <= descent <= 15.0
    lv = [np.count_nonzero(np.asarray(img.dataobj) == 3) for img in images]
    assert int(np.argmax(lv)) + 1 == int(cfg["ED"]) and int(np.argmin(lv)) + 1 == int(cfg["ES"])
    assert all(np.asarray(img.dataobj).dtype == np.uint8 for img in images)
    # The short-axis slice normal is the long axis: toward the apex, left-anterior-inferior.
    normal = images[0].affine[:3, 2] / 8.0
    assert normal[0] < 0 and normal[1] > 0 and normal[2] < 0


def test_biventricular_parameters_vary_within_documented_ranges():
    a, b = phantom_beating.sample_biventricular_params(rng(0)), phantom_beating.sample_biventricular_params(rng(1))
    assert a.keys() == b.keys() == phantom_beating.BIVENTRICULAR_RANGES.keys()
    assert sum(a[k] != b[k] for k in a) >= 15
    for name, (low, high) in phantom_beating.BIVENTRICULAR_RANGES.items():
        assert low <= a[name] <= high and low <= b[name] <= high
