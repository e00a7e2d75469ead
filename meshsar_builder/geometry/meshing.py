"""Label maps to closed surface meshes: signed distance, isotropic resampling, marching cubes.

DESIGN section 6. The signed distance of the union mask (EDT on both sides, in
mm) is resampled (cubic B-spline) to isotropic spacing and smoothed lightly before
marching cubes: the distance to voxel centres is jagged, and thick ACDC slices
would stair-step without the resampling.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage import measure
from skimage.graph import MCP_Geometric

from meshsar_builder.geometry.closest import point_to_surface
from meshsar_builder.geometry.digital_topology import ball_core
from meshsar_builder.geometry.label_repair import (
    CHAMBERS, check_border, clean_labels, correct_handles, fill_junction_walls, lv_gaps_to_myo, repair_summary,
    separate_contacts)
from meshsar_builder.geometry.structures import STRUCTURES
from meshsar_builder.pipeline.errors import InputError, MeshError

_NAMES = {v: k for k, v in STRUCTURES.items()}
# Each great vessel and the chamber(s) whose valve it leaves from.
VALVE_CHAMBERS: dict[str, tuple[str, ...]] = {"aorta": ("lv",), "pa": ("rv",)}
# Step between the slabs of equal distance from the valve whose centroids trace the centreline.
_SLAB_MM = 2.0
# The cut's normal: the centreline's direction over this arclength either side of the cut.
_TANGENT_MM = 4.0


@dataclass(frozen=True)
class MeshingParams:
    spacing_mm: float = 1.0  # isotropic resampling step of the signed distance
    sigma_mm: float = 1.0  # Gaussian smoothing of the resampled signed distance
    # Great vessels cut at this length (mm) from their valve along their centreline, e.g.
    # {aorta = 30, pa = 25}: label maps' vessel lengths depend on the field of view and the annotator.
    vessel_length_mm: dict[str, float] = field(default_factory=dict)
    # Topology repair (label_repair): width of the gap opened where structures touch without a
    # junction, wide enough to survive the smoothing: at sigma 1 mm, 2 mm gaps closed in 6 of 12
    # oblique contacts, 2.5 mm in none (docs/topology.md); 3 mm leaves a margin for curved ones.
    gap_mm: float = 3.0
    wall_mm: float = 3.0  # unlabelled walls between joined structures are filled where both are this near
    island_fraction: float = 0.05  # a label's components below this fraction of it are dropped
    max_volume_change: float = 0.02  # largest change of a chamber's or the myocardium's volume
    max_surface_shift_mm: float = 0.5  # largest two-sided mean distance to the unrepaired surface
    # A thick-slice stack that cuts the shape (its base) ends flat at its last slice's face (_cut_flat): the
    # volume within 2 % where the interpolation alone rounds the base 1-2 % short (docs/topology.md).
    flat_ends: bool = True
    # A chamber (or the myocardium) cut by the map's border over more than this (mm^2) fails the item (label_repair.
    # check_border; not a thick-slice stack's slice ends: its cut base); inf: no check.
    max_border_mm2: float = 20.0

    def __post_init__(self):
        if not self.spacing_mm > 0:
            raise ValueError(f"spacing_mm: must be > 0, got {self.spacing_mm}")
        if not self.sigma_mm >= 0:
            raise ValueError(f"sigma_mm: must be >= 0, got {self.sigma_mm}")
        unknown = sorted(set(self.vessel_length_mm) - set(VALVE_CHAMBERS))
        if unknown:
            raise ValueError(f"vessel_length_mm: unknown vessel {unknown[0]!r}; vessels: {sorted(VALVE_CHAMBERS)}")
        for vessel, length in self.vessel_length_mm.items():
            if not 0 < length < 1000:
                raise ValueError(f"vessel_length_mm: {vessel} must be in (0, 1000) mm, got {length}")
        for key in ("gap_mm", "wall_mm", "max_surface_shift_mm"):
            if not 0 <= getattr(self, key) <= 20:
                raise ValueError(f"{key}: must be in [0, 20] mm, got {getattr(self, key)}")
        if not self.max_border_mm2 >= 0:
            raise ValueError(f"max_border_mm2: must be >= 0, got {self.max_border_mm2}")
        for key in ("island_fraction", "max_volume_change"):
            if not 0 <= getattr(self, key) < 1:
                raise ValueError(f"{key}: must be in [0, 1), got {getattr(self, key)}")


class Surface(NamedTuple):
    verts: np.ndarray  # (n, 3) float64, RAS mm
    faces: np.ndarray  # (m, 3) int64, outward-oriented
    labels: np.ndarray  # (n,) uint8, canonical structure id of the nearest labelled voxel
    repair: dict  # what the topology repair changed and its figures (empty: nothing needed)


def signed_distance(mask: np.ndarray, voxel_mm: np.ndarray) -> np.ndarray:
    """Signed distance to the mask boundary, mm: negative inside, zero halfway between voxel centres.

    mask : (X, Y, Z) bool, voxel_mm : (3,) float -> (X, Y, Z) float32
    """
    outside = ndimage.distance_transform_edt(~mask, sampling=voxel_mm)
    inside = ndimage.distance_transform_edt(mask, sampling=voxel_mm)
    return (outside - inside).astype(np.float32)


class IsoGrid(NamedTuple):
    """The smoothed signed distance on the isotropic meshing grid and its map to the label map."""

    values: np.ndarray  # (I, J, K) float32 mm, negative inside
    origin: np.ndarray  # (3,) label-map voxel index of grid point (0, 0, 0)
    step: np.ndarray  # (3,) label-map voxels per grid step, per axis
    affine: np.ndarray  # (4, 4) label-map voxel -> RAS mm

    @property
    def spacing_mm(self) -> float:
        return float(np.linalg.norm(self.affine[:3, :3], axis=0)[0] * self.step[0])

    def to_world(self, index: np.ndarray) -> np.ndarray:
        """Grid indices (n, 3), fractional allowed -> RAS mm (n, 3)."""
        vox = self.origin + np.asarray(index, float) * self.step
        return vox @ self.affine[:3, :3].T + self.affine[:3, 3]


# Edge padding before the spline filter, as scipy's map_coordinates pads for mode "nearest" (its npad).
SPLINE_PAD = 12


def resample_cubic(values: np.ndarray, axes: list[np.ndarray]) -> np.ndarray:
    """values (X, Y, Z) float resampled by cubic B-spline onto the grid of axes (3 x (m_i,) fractional voxel
    positions within [0, n_i - 1]): (m_0, m_1, m_2) float64.

    What ndimage.map_coordinates(values, meshgrid(*axes), order=3, mode="nearest") gives (the same edge padding and
    prefilter; 4e-15 from it in the tests), but one axis at a time, four taps each, since the grid is a tensor
    product: a frame of 1.5 x 1.5 x 8 mm voxels onto 1 mm took 0.44 s as 64 taps per point.
    """
    out = ndimage.spline_filter(np.pad(values, SPLINE_PAD, mode="edge"), order=3, output=np.float64, mode="nearest")
    # The axis that grows most last, so the passes before it run on the smaller arrays.
    for axis in sorted(range(3), key=lambda a: len(axes[a]) / values.shape[a]):
        x = np.asarray(axes[axis], dtype=np.float64) + SPLINE_PAD
        first = np.floor(x).astype(np.intp) - 1
        t = x - first - 1
        weights = ((1 - t) ** 3 / 6, (3 * t**3 - 6 * t**2 + 4) / 6, (-3 * t**3 + 3 * t**2 + 3 * t + 1) / 6, t**3 / 6)
        along = np.moveaxis(out, axis, 0)
        summed = weights[0][:, None, None] * along[first]
        for tap in (1, 2, 3):
            summed += weights[tap][:, None, None] * along[first + tap]
        out = np.moveaxis(summed, 0, axis)
    return out


# A stack whose slices are this many times thicker than its pixels are wide is a thick-slice stack (short-axis cine).
THICK_SLICE_RATIO = 2.0


# A stack end whose last slice holds at least this share of the area of the slice before it is a cut: the shape
# goes on beyond the stack (the base of a short-axis stack). A smaller one closes within its slab (an apex, a pole).
CUT_AREA_RATIO = 0.9
# Slices beyond a cut end set by _cut_flat: a cubic B-spline's prefilter weights fall 3.7x a sample, so a fourth
# would move the crossing by under 1 %. The padding holds them (3 slices at least: iso_grid's margin).
BEYOND_SLICES = 3


def _cut_flat(sdf: np.ndarray, mask: np.ndarray, axis: int) -> None:
    """Where a thick-slice stack cuts the shape (CUT_AREA_RATIO), the surface ends flat at the end slice's outer
    face: beyond each inside column of that slice, at the value d inside it, the outside values of the next
    BEYOND_SLICES slices become at most d, 3 d, 5 d, as if the field went on linearly through the face, so the
    interpolating spline crosses zero on it. An end that closes keeps the interpolated, rounded end. In place; sdf
    (X, Y, Z) float, mask (X, Y, Z) bool, on one (padded) grid; axis : the slice axis.

    Why: between the basal slice's centre, 0.75 mm (in plane) from the boundary at its rim, and the outside centre
    beyond it, 5 mm (through the plane) at 10 mm slices, the interpolated field crossed zero about 4 mm short of the
    face and rounded the whole rim: -35 % of the cross-section 1 mm above an LV-like base, about 2 % of its volume.
    With the first slice beyond alone set to d, a rim column's d beside the distance-map's 20 mm one slice further
    made the cubic spline overshoot: 2.4 mm past an LV-like base at 10 mm slices, 2.8 mm on real ventricles.
    """
    field, inside = (np.moveaxis(a, axis, -1) for a in (sdf, mask))  # views
    area = inside.sum(axis=(0, 1))
    occupied = np.flatnonzero(area)
    if len(occupied) < 2:
        return
    for end, out in ((occupied[0], -1), (occupied[-1], 1)):
        if area[end] >= CUT_AREA_RATIO * area[end - out]:
            column = inside[..., end]
            depth = -field[..., end][column]  # > 0
            for k in range(BEYOND_SLICES):  # the padding holds them
                outside = field[..., end + out * (k + 1)]
                outside[column] = np.minimum(outside[column], (2 * k + 1) * depth)


def iso_grid(mask: np.ndarray, affine: np.ndarray, params: MeshingParams, name: str = "label map") -> IsoGrid:
    """Signed distance of a mask resampled to `spacing_mm` and smoothed: the field meshed at 0. With
    params.flat_ends (the default), in a thick-slice stack (THICK_SLICE_RATIO), an end where the stack cuts
    the shape ends flat at its slice's face (_cut_flat).

    mask : (X, Y, Z) bool, affine : (4, 4) voxel -> RAS mm; name : the input, for errors.
    """
    voxel_mm = np.linalg.norm(affine[:3, :3], axis=0)
    step = params.spacing_mm / voxel_mm  # new-grid step in voxel units, per axis
    # Crop to the mask with a margin wide enough for the smoothing kernel and the zero level.
    margin_mm = 3 * params.sigma_mm + 2 * params.spacing_mm + 2 * voxel_mm.max()
    pad = np.ceil(margin_mm / voxel_mm).astype(int)
    nz = np.argwhere(mask)
    lo = nz.min(axis=0) - pad
    hi = nz.max(axis=0) + pad + 1
    padded = np.zeros(hi - lo, dtype=bool)
    src_lo = np.maximum(lo, 0)
    src_hi = np.minimum(hi, mask.shape)
    padded[tuple(slice(a - l, b - l) for a, b, l in zip(src_lo, src_hi, lo))] = mask[
        tuple(slice(a, b) for a, b in zip(src_lo, src_hi))
    ]
    sdf = signed_distance(padded, voxel_mm)
    slice_axis = int(np.argmax(voxel_mm))
    if params.flat_ends and voxel_mm[slice_axis] >= THICK_SLICE_RATIO * voxel_mm.min():
        _cut_flat(sdf, padded, slice_axis)
    axes = [np.arange(0, n - 1 + 1e-9, s) for n, s in zip(padded.shape, step)]
    # Cubic B-spline, not linear: across thick slices (5-10 mm short-axis stacks) a linear blend
    # of the distance cuts chords inside a convex surface. Measured at 6/8/10 mm slices: a 30 mm
    # sphere's volume -1.7/-3.1/-3.5 % linear, -1.0/-1.3/-1.4 % cubic; a half-spheroid LV
    # (r 25, L 70, base on a slice boundary) -1.9/-3.0/-4.0 % against -1.2/-1.7/-1.9 %, with
    # the mean distance to the true surface no worse; with its base cut flat (flat_ends), -0.3/+0.0/+0.7 %
    # and closer to the true surface (docs/topology.md).
    iso = resample_cubic(sdf, axes).astype(np.float32)
    if params.sigma_mm > 0:
        iso = ndimage.gaussian_filter(iso, params.sigma_mm / params.spacing_mm, mode="nearest")
    if not (iso.min() < 0 < iso.max()):
        raise MeshError(f"{name}: mask vanished after resampling and smoothing (structure thinner than the smoothing?)")
    return IsoGrid(iso, lo.astype(float), step, np.asarray(affine, float))


def contour(grid: IsoGrid) -> tuple[np.ndarray, np.ndarray]:
    """Largest connected surface of the zero level of an IsoGrid, in world mm.

    Returns verts (n, 3) float64, faces (m, 3) int64 with outward normals.
    """
    verts, faces, _, _ = measure.marching_cubes(grid.values, level=0.0)
    mesh = trimesh.Trimesh(grid.to_world(verts), faces, process=True)
    parts = mesh.split(only_watertight=False)
    # Signed volumes by the divergence theorem: trimesh's mass properties divide by the volume
    # and warn on the flat slivers marching cubes leaves at the edge of thick slices.
    mesh = max(parts, key=lambda m: abs(signed_volume(m.vertices, m.faces))) if len(parts) > 1 else mesh
    if signed_volume(mesh.vertices, mesh.faces) < 0:
        mesh.invert()
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by a closed surface, positive for outward faces. verts (n, 3), faces (m, 3)."""
    a, b, c = (np.asarray(verts, np.float64)[np.asarray(faces)[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def mask_surface(mask: np.ndarray, affine: np.ndarray, params: MeshingParams) -> tuple[np.ndarray, np.ndarray]:
    """Largest connected surface of a mask, in world mm.

    mask : (X, Y, Z) bool, affine : (4, 4) voxel -> RAS mm
    Returns verts (n, 3) float64, faces (m, 3) int64 with outward normals.
    """
    return contour(iso_grid(mask, affine, params))


def is_closed_genus0(verts: np.ndarray, faces: np.ndarray) -> tuple[bool, int, bool]:
    """(ok, euler characteristic, watertight) of a surface. verts : (n, 3), faces : (m, 3)."""
    mesh = trimesh.Trimesh(verts, faces, process=False)
    euler = int(mesh.euler_number)
    watertight = bool(mesh.is_watertight)
    return watertight and euler == 2, euler, watertight


def labels_to_surface(
    labels: np.ndarray, affine: np.ndarray, structures: list[str], params: MeshingParams, name: str = "label map"
) -> Surface:
    """Mesh the union of `structures` of a canonical label map, its topology repaired by anatomy.

    labels : (X, Y, Z) uint8 canonical ids, affine : (4, 4). The repair (label_repair) cleans
    each label, fills the walls between joined structures and opens a gap where structures
    touch without a junction; a handle left is cut or filled on the meshing grid. Raises
    InputError when none of the structures is present, MeshError when no closed genus-0
    surface results or the repair would change a chamber's volume or move the surface more
    than the params allow (the message gives the figures and where a handle is).
    """
    if params.vessel_length_mm:
        labels = trim_vessels(labels, affine, params.vessel_length_mm, name)
    ids = [STRUCTURES[s] for s in structures]
    chosen = np.where(np.isin(labels, ids), labels, 0).astype(np.uint8)
    if not chosen.any():
        present = sorted(k for k, v in STRUCTURES.items() if (labels == v).any())
        raise InputError(f"{name}: none of the structures {structures} present (found: {present})")
    # One voxel thick along an axis (a long-axis cine view is a single slice): no solid to mesh, which the smoothing
    # would only report as a vanished mask.
    spans = [int(np.ptp(index)) + 1 for index in np.nonzero(chosen)]
    if min(spans) < 2:
        axis = int(np.argmin(spans))
        raise InputError(f"{name}: the structures {structures} are one voxel thick along voxel axis {axis} (label map "
                         f"shape {labels.shape}): a single slice has no 3-D surface; mesh a stack of slices")
    missing = [s for s in structures if not (chosen == STRUCTURES[s]).any()]
    if missing:
        present = sorted(k for k, v in STRUCTURES.items() if (labels == v).any())
        raise InputError(f"{name}: the structures {missing} are missing from the label map (found: {present}); a "
                         f"surface without them would not be the anatomy asked for: list only the structures every "
                         f"map has")
    voxel_mm = np.linalg.norm(affine[:3, :3], axis=0)
    thick = voxel_mm.max() >= THICK_SLICE_RATIO * voxel_mm.min()  # a stack's ends cut the shape by design (flat_ends)
    check_border(chosen, voxel_mm, int(np.argmax(voxel_mm)) if thick else None, params.max_border_mm2, name)
    union = ndimage.binary_fill_holes(chosen > 0)
    pieces = _pieces_apart(union, chosen, affine, structures, params.island_fraction, name)
    plain = contour(iso_grid(union, affine, params, name))
    if is_closed_genus0(*plain)[0]:
        # Already genus 0: no repair, so a surface that needs none is never changed by one.
        return _surface(*plain, nearest_labels(plain[0], chosen, chosen > 0, affine), pieces)
    record: dict = {**pieces, "euler_before": int(trimesh.Trimesh(*plain, process=False).euler_number)}
    # The repair's distance maps need only the heart and a margin, not a CT's whole field of view.
    chosen, affine = _crop(chosen, affine, params.gap_mm + params.wall_mm)
    repaired, steps, gaps, walls = repair_labels(chosen, np.linalg.norm(affine[:3, :3], axis=0), params)
    for contact in steps["contacts_cut"]:
        world = np.asarray(contact.pop("position_index")) @ affine[:3, :3].T + affine[:3, 3]
        contact["position_mm"] = [round(float(c), 2) for c in world]
    record.update(steps)
    grid = iso_grid(ndimage.binary_fill_holes(repaired > 0), affine, params, name)
    handles: list[dict] = []
    # Marching cubes joins voxels across a saddle as one or the other adjacency would: try the
    # solid's 6-adjacency first (thin diagonal contacts count as apart), then 26.
    for six in (None, True, False):
        if six is not None:
            handles += _correct_grid_handles(grid, repaired, six)
        verts, faces = contour(grid)
        ok, euler, watertight = is_closed_genus0(verts, faces)
        if ok:
            break
    record["handles"] = handles
    if not ok:
        raise MeshError(f"{name}: surface is not closed genus 0 (euler={euler}, watertight={watertight}) after "
                        f"topology repair; handles left at {_handles_left(grid, repaired)}; {repair_summary(record)}")
    record.update(_repair_figures(chosen, np.where(walls, 0, repaired), handles, gaps, verts, faces, plain, affine, params))
    _check_repair(record, name, params)
    return _surface(verts, faces, nearest_labels(verts, repaired, repaired > 0, affine), record)


def _pieces_apart(union: np.ndarray, chosen: np.ndarray, affine: np.ndarray, structures: list[str],
                  island_fraction: float, name: str) -> dict:
    """The record of the union's pieces apart from its largest, which the surface leaves out (contour keeps one).

    union : (X, Y, Z) bool, chosen : (X, Y, Z) uint8 canonical ids. Raises InputError when a
    structure has more than island_fraction of its voxels apart: it does not touch the rest (the
    LV and RV pools without the myocardium between them), so one closed surface cannot hold it.
    Smaller pieces are islands, left out and recorded ({"pieces_apart_ml": {structure: ml}}).
    """
    # The box of the union only (a CT's field of view is mostly background): int32 labels of a whole
    # 512 x 512 x 248 volume would take 260 MB.
    box = tuple(slice(ends[0], ends[-1] + 1) for ends in
                (np.flatnonzero(union.any(axis=tuple(a for a in range(3) if a != axis))) for axis in range(3)))
    union, chosen = union[box], chosen[box]
    pieces, count = ndimage.label(union, structure=np.ones((3, 3, 3)))  # diagonal contacts count as touching
    if count <= 1:
        return {}
    apart = pieces != np.bincount(pieces.ravel())[1:].argmax() + 1
    ml = abs(np.linalg.det(affine[:3, :3])) / 1000
    lost, too_much = {}, []
    for structure in structures:
        voxels = chosen == STRUCTURES[structure]
        away, whole = int(np.count_nonzero(voxels & apart)), int(np.count_nonzero(voxels))
        if away:
            lost[structure] = round(away * ml, 3)
            if away > island_fraction * whole:
                too_much.append(f"{structure} ({away * ml:.1f} of {whole * ml:.1f} ml)")
    if too_much:
        raise InputError(f"{name}: the structures {structures} form {count} separate pieces, and one closed surface "
                         f"holds only the largest; apart from it lie {', '.join(too_much)}, more than island_fraction "
                         f"= {island_fraction} of each: add the structure that joins them (the myocardium between the "
                         f"LV and RV pools) or mesh them as separate sources")
    return {"pieces_apart_ml": lost}


def _surface(verts: np.ndarray, faces: np.ndarray, labels: np.ndarray, record: dict) -> Surface:
    """The Surface, with a biventricular surface's stray LV patches relabelled (lv_gaps_to_myo, recorded)."""
    labels, relabelled = lv_gaps_to_myo(verts, faces, labels)
    return Surface(verts, faces, labels, record | ({"lv_patches_relabelled": relabelled} if relabelled else {}))


def _crop(labels: np.ndarray, affine: np.ndarray, margin_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The box of the non-zero labels plus margin_mm (two voxels at least), and its affine."""
    voxel_mm = np.linalg.norm(affine[:3, :3], axis=0)
    pad = np.ceil(margin_mm / voxel_mm).astype(int) + 2
    nz = np.argwhere(labels)
    lo, hi = np.maximum(nz.min(axis=0) - pad, 0), np.minimum(nz.max(axis=0) + pad + 1, labels.shape)
    shifted = np.array(affine, float)
    shifted[:3, 3] = affine[:3, :3] @ lo + affine[:3, 3]
    return labels[tuple(slice(a, b) for a, b in zip(lo, hi))], shifted


def repair_labels(labels: np.ndarray, voxel_mm: np.ndarray,
                  params: MeshingParams) -> tuple[np.ndarray, dict, np.ndarray, np.ndarray]:
    """The label-level steps of the repair, in order (label_repair): clean, walls, contacts.

    labels : (X, Y, Z) uint8 canonical ids, voxel_mm : (3,). Returns the repaired labels, the
    record of each step, and (X, Y, Z) bool masks of the voxels the contact gaps removed and of
    the wall voxels filled between joined structures.
    """
    cleaned, islands = clean_labels(labels, params.island_fraction)
    walled, walls, wall_mask = fill_junction_walls(cleaned, voxel_mm, params.wall_mm)
    separated, contacts, gaps = separate_contacts(walled, voxel_mm, params.gap_mm)
    return separated, {"labels": islands, "walls_filled": walls, "contacts_cut": contacts}, gaps, wall_mask


def _correct_grid_handles(grid: IsoGrid, labels: np.ndarray, six: bool) -> list[dict]:
    """Cut or fill the handles of the meshing grid's solid in place (grid.values); describe each.

    A cut voxel is pushed just outside the zero level, a filled one just inside, so the
    contour passes between them and their neighbours.
    """
    structure = ndimage.generate_binary_structure(3, 1 if six else 3)
    comp, n = ndimage.label(grid.values < 0, structure=structure)
    if n == 0:
        return []
    solid = comp == np.bincount(comp.ravel())[1:].argmax() + 1
    solid = ndimage.binary_fill_holes(solid)
    fixed, changes = correct_handles(solid, -grid.values.astype(np.float64), six)
    nudge = np.float32(0.25 * grid.spacing_mm)
    grid.values[solid & ~fixed] = np.maximum(grid.values[solid & ~fixed], nudge)
    grid.values[fixed & ~solid] = np.minimum(grid.values[fixed & ~solid], -nudge)
    for change in changes:
        world = grid.to_world(np.asarray(change.pop("index"))[None])[0]
        change["position_mm"] = [round(float(c), 2) for c in world]
        change["structures"] = _structures_near(world, labels, grid.affine)
        change["volume_mm3"] = round(change["voxels"] * grid.spacing_mm**3, 1)
    return changes


def _handles_left(grid: IsoGrid, labels: np.ndarray, most: int = 5) -> list[str]:
    """Where the meshing grid's solid still has handles: the thinnest cut through each (the
    pieces ball_core leaves out, largest first), with the structures around it."""
    structure = ndimage.generate_binary_structure(3, 3)
    comp, n = ndimage.label(grid.values < 0, structure=structure)
    if n == 0:
        return []
    solid = ndimage.binary_fill_holes(comp == np.bincount(comp.ravel())[1:].argmax() + 1)
    cuts, count = ndimage.label(solid & ~ball_core(solid, -grid.values.astype(np.float64), six=False), structure=structure)
    sizes = np.bincount(cuts.ravel())[1:]
    found = []
    for c in np.argsort(sizes)[::-1][:most] + 1:
        world = grid.to_world(np.argwhere(cuts == c).mean(axis=0)[None])[0]
        found.append(f"{[round(float(x), 1) for x in world]} mm ({'/'.join(_structures_near(world, labels, grid.affine))})")
    return found


def _structures_near(point: np.ndarray, labels: np.ndarray, affine: np.ndarray, radius_mm: float = 4.0) -> list[str]:
    """Structures with a voxel within radius_mm of a world point, nearest first (at least the
    nearest one, however far)."""
    voxel_mm = np.linalg.norm(affine[:3, :3], axis=0)
    centre = np.linalg.solve(affine[:3, :3], point - affine[:3, 3])
    reach = np.ceil(radius_mm / voxel_mm).astype(int)
    lo = np.clip(np.floor(centre).astype(int) - reach, 0, labels.shape)
    hi = np.clip(np.ceil(centre).astype(int) + reach + 1, 0, labels.shape)
    box = labels[tuple(slice(a, b) for a, b in zip(lo, hi))]
    idx = np.argwhere(box > 0)
    dist = np.linalg.norm((idx + lo - centre) * voxel_mm, axis=1)
    if len(dist) and not (dist <= radius_mm).any():
        return _structures_near(point, labels, affine, 2 * radius_mm)
    order = np.argsort(dist[dist <= radius_mm], kind="stable")
    ids = box[tuple(idx[dist <= radius_mm][order].T)]
    return [_NAMES[i] for i in dict.fromkeys(ids.tolist())]


def _repair_figures(before: np.ndarray, after: np.ndarray, handles: list[dict], gaps: np.ndarray,
                    verts: np.ndarray, faces: np.ndarray, plain: tuple[np.ndarray, np.ndarray],
                    affine: np.ndarray, params: MeshingParams) -> dict:
    """Each structure's relative volume change, and the surface's shift from the unrepaired one.

    before, after : (X, Y, Z) uint8 labels (after without the filled walls, which are wall
    tissue, not chamber volume); handles: their cuts (volume taken from the nearest
    structure) and fills (added to it); plain : the unrepaired union's (verts, faces). The shift
    is the two-sided mean distance between the surfaces from 20,000 area-weighted points each
    way, leaving out points within gap_mm + 2 spacings of the contact gaps (the new gap walls).
    """
    voxel_ml = abs(np.linalg.det(affine[:3, :3]))
    n = max(STRUCTURES.values()) + 1
    vol_before = np.bincount(before.ravel(), minlength=n) * voxel_ml
    vol_after = np.bincount(after.ravel(), minlength=n) * voxel_ml
    for h in handles:
        if h["structures"]:
            vol_after[STRUCTURES[h["structures"][0]]] += h["volume_mm3"] * (1 if h["kind"] == "fill" else -1)
    change = {name: round(float(vol_after[i] / vol_before[i] - 1), 5) for name, i in STRUCTURES.items() if vol_before[i]}
    gap_world = np.argwhere(gaps) @ affine[:3, :3].T + affine[:3, 3]
    near_gap = cKDTree(gap_world) if len(gap_world) else None
    reach = params.gap_mm + 2 * params.spacing_mm
    means = []
    for (v_from, f_from), (v_to, f_to) in (((verts, faces), plain), (plain, (verts, faces))):
        points, _ = trimesh.sample.sample_surface(trimesh.Trimesh(v_from, f_from, process=False), 20000, seed=0)
        if near_gap is not None:
            points = points[near_gap.query(points)[0] > reach]
        means.append(float(point_to_surface(points, v_to, f_to)[0].mean()) if len(points) else 0.0)
    return {"volume_change": change, "surface_shift_mm": round(float(np.mean(means)), 4)}


def _check_repair(record: dict, name: str, params: MeshingParams) -> None:
    """MeshError naming the figures when the repair changed a chamber or the surface too much."""
    over = {s: c for s, c in record["volume_change"].items() if s in CHAMBERS and abs(c) > params.max_volume_change}
    if over or record["surface_shift_mm"] > params.max_surface_shift_mm:
        raise MeshError(
            f"{name}: topology repair too large: volume change {over or 'within bounds'} "
            f"(limit {params.max_volume_change:.0%}), surface shift {record['surface_shift_mm']} mm "
            f"(limit {params.max_surface_shift_mm} mm); repair: {repair_summary(record)}")


def trim_vessels(labels: np.ndarray, affine: np.ndarray, lengths: dict[str, float], name: str = "label map") -> np.ndarray:
    """Cut each great vessel by a plane `lengths[vessel]` mm from its valve, along its centreline.

    labels : (X, Y, Z) uint8 canonical ids, affine : (4, 4) voxel -> RAS mm,
    lengths : {"aorta" | "pa": mm}. Returns a copy with the cut-off parts set to 0.
    The valve is the vessel's contact with its chamber's blood pool (VALVE_CHAMBERS). The
    centreline is traced by the centroids of slabs of equal geodesic distance from the valve
    inside the vessel (26-connected, mm), starting at the valve's centroid; the cut is where its
    arclength reaches the length, by the plane through that point normal to the centreline there.
    What lies beyond the plane, and any part of the vessel not connected to the valve, is
    removed: the vessel ends in a flat cap and keeps no downstream contact with other structures.
    A vessel shorter than its length loses only its unconnected parts; a map without the vessel
    is left as is.
    MeshError when a vessel touches no chamber of its valve.
    """
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    out = labels.copy()
    for vessel, length in sorted(lengths.items()):
        mask = labels == STRUCTURES[vessel]
        if not mask.any():
            continue
        chamber = np.isin(labels, [STRUCTURES[c] for c in VALVE_CHAMBERS[vessel]])
        valve = mask & ndimage.binary_dilation(chamber)
        if not valve.any():
            raise MeshError(f"{name}: {vessel} touches no {'/'.join(VALVE_CHAMBERS[vessel])}, so it has no valve to measure from")
        # Work in the vessel's bounding box: geodesic distance (mm) from the valve inside the vessel.
        box = ndimage.find_objects(mask.astype(np.uint8))[0]
        sub, valve_sub = mask[box], valve[box]
        offset = np.array([s.start for s in box])
        distance, _ = MCP_Geometric(np.where(sub, 1.0, np.inf), sampling=tuple(spacing)).find_costs(np.argwhere(valve_sub))
        # Parts of the vessel not connected to the valve (infinite distance) are dropped below.
        inside = np.argwhere(sub & np.isfinite(distance))
        d = distance[tuple(inside.T)]
        world = (inside + offset) @ affine[:3, :3].T + affine[:3, 3]
        # Centreline: the valve centroid, then slab centroids every _SLAB_MM of distance.
        levels = np.arange(_SLAB_MM, d.max() + _SLAB_MM, _SLAB_MM)
        which = np.clip(np.round(d / _SLAB_MM).astype(int), 0, len(levels))
        sums = np.zeros((len(levels) + 1, 3))
        np.add.at(sums, which, world)
        counts = np.bincount(which, minlength=len(levels) + 1)
        centreline = np.vstack([world[valve_sub[tuple(inside.T)]].mean(axis=0), (sums[1:] / np.maximum(counts[1:, None], 1))[counts[1:] > 0]])
        level = np.concatenate([[0.0], levels[counts[1:] > 0]])
        arclength = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centreline, axis=0), axis=1))])
        if arclength[-1] < length + _TANGENT_MM:
            out[box][sub & ~np.isfinite(distance)] = 0
            continue  # shorter than the cut length
        point = np.array([np.interp(length, arclength, centreline[:, k]) for k in range(3)])
        ahead, behind = (np.array([np.interp(s, arclength, centreline[:, k]) for k in range(3)])
                         for s in (length + _TANGENT_MM, max(length - _TANGENT_MM, 0.0)))
        normal = (ahead - behind) / np.linalg.norm(ahead - behind)
        # Beyond the plane, and past the first half of the length (a vessel curving back near
        # its root keeps that part): cut. Then keep only what still connects to the valve.
        cut = ((world - point) @ normal > 0) & (d > 0.5 * np.interp(length, arclength, level))
        kept = np.zeros_like(sub)
        kept[tuple(inside[~cut].T)] = True
        components, _ = ndimage.label(kept, structure=np.ones((3, 3, 3)))
        attached = np.unique(components[valve_sub & kept])
        kept &= np.isin(components, attached[attached > 0])
        out[box][sub & ~kept] = 0
    return out


def nearest_labels(verts: np.ndarray, labels: np.ndarray, mask: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Label of the nearest boundary voxel of `mask` for each vertex.

    verts : (n, 3) RAS mm, labels : (X, Y, Z) uint8, mask : (X, Y, Z) bool -> (n,) uint8
    """
    boundary = mask & ~ndimage.binary_erosion(mask)
    idx = np.argwhere(boundary)
    centres = idx @ affine[:3, :3].T + affine[:3, 3]
    _, nearest = cKDTree(centres).query(verts)
    return labels[tuple(idx[nearest].T)].astype(np.uint8)


def long_axis_landmarks(labels: np.ndarray, affine: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, float]:
    """Apex and base-plane position of the LV of a canonical label map, for motion over a cycle.

    labels : (X, Y, Z) uint8 canonical ids, affine : (4, 4) voxel -> RAS mm, axis : (3,) the long
    axis, either way (for a short-axis stack, its slice normal, whose sign is the file's slice
    order): it is turned toward the apex, the end of the LV (blood and wall) farther from its
    centroid, since the ventricle narrows to the apex (a half-ellipsoid's centroid lies 3/8 of
    its length from the base).
    Returns apex (3,) RAS mm, the mean of the myocardial voxels within 1 mm (along the axis) of
    the most apical one, and base (float) mm along the axis toward the apex, the most basal LV
    voxel (blood or wall). Voxel centres: both are quantised to the voxel size along the axis.
    """
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    myo = np.argwhere(labels == STRUCTURES["myo"]) @ affine[:3, :3].T + affine[:3, 3]
    lv = np.argwhere(np.isin(labels, (STRUCTURES["myo"], STRUCTURES["lv"]))) @ affine[:3, :3].T + affine[:3, 3]
    if not len(myo):
        raise InputError("long-axis landmarks: no LV myocardium in the label map")
    along = lv @ axis
    if along.max() - along.mean() < along.mean() - along.min():
        axis = -axis
    depth = myo @ axis
    return myo[depth >= depth.max() - 1.0].mean(axis=0), float((lv @ axis).min())


def transfer_labels(src_verts: np.ndarray, src_labels: np.ndarray, dst_verts: np.ndarray) -> np.ndarray:
    """Label of the nearest source vertex for each destination vertex.

    src_verts : (n, 3), src_labels : (n,) uint8, dst_verts : (k, 3) -> (k,) uint8
    """
    _, nearest = cKDTree(src_verts).query(dst_verts)
    return np.asarray(src_labels, dtype=np.uint8)[nearest]
