"""Built-in whole-heart phantom (MM-WHS labels), seeded and parametric.

Signed-distance ellipsoids (ventricles, atria) and tubes along smooth curves (aorta, pulmonary
artery) are placed in RAS+ millimetres around the LV base centre, evaluated vectorised on the
voxel grid and written as NIfTI in the MM-WHS layout, so the real-data loader reads them
unchanged. The chambers and an unlabelled atrioventricular plate are smooth-unioned into one
body; each vessel is smooth-unioned with that body only (never with the other vessel), and is cut
off where, having left the body, it would come back within `_VESSEL_GAP_MM` of it or of the
aorta. So the union of all labels is one solid without handles (genus 0). Labels follow a fixed
precedence; voxels of the blending fillets take the label of the nearest structure.

The beating biventricular phantom (ACDC layout) is in `phantom_beating`.
"""

from __future__ import annotations

import gzip
from dataclasses import dataclass
from pathlib import Path

import nibabel as nib
import numpy as np
from scipy import ndimage

from meshsar_builder.pipeline.io import write_bytes

# MM-WHS label codes.
LV_MYO, LA, LV_BLOOD, RA, RV, AORTA, PULMONARY_ARTERY = 205, 420, 500, 550, 600, 820, 850

# Smooth-union radius between chambers: fills the crevices between them, as epicardial fat does.
_CHAMBER_BLEND_MM = 6.0
# Smooth-union radius between a vessel and the chamber body: a fillet at the vessel's root, wide
# enough to fill the pockets where a vessel root grazes two chambers at once (else a tunnel).
_VESSEL_BLEND_MM = 8.0
# A vessel that has left the body stays this far from it and from the other vessel. It must exceed
# half the vessel blend (else the fillet bridges the gap) and survive the meshing stage's 1 mm
# Gaussian smoothing and a 2x downsampling of the mask.
_VESSEL_GAP_MM = 7.0
# A fall in clearance smaller than this is the obstacle's curvature, not a vessel turning back.
_RETURN_TOLERANCE_MM = 0.5
# Signed distances beyond this change no blend and no label: each primitive is evaluated only in
# its bounding box padded by it, and clamped to it (at least twice the largest blend radius).
_FAR_MM = 16.0
# Curves are sampled at this arclength step for the clearance tests.
_CURVE_STEP_MM = 1.0

# Whole-heart shape parameters: name -> (low, high), drawn uniformly. Adult, end-diastole.
WHOLE_HEART_RANGES: dict[str, tuple[float, float]] = {
    # LV base (mitral plane) to epicardial apex; adult end-diastolic long axis 80-100 mm.
    "lv_length_mm": (80.0, 100.0),
    # LV end-diastolic internal diameter 44-56 mm (ASE/EACVI normal adult range).
    "lv_cavity_radius_mm": (22.0, 28.0),
    # Short-axis cavity aspect ratio; end-diastolic cross-sections are nearly circular.
    "lv_cavity_ellipticity": (0.9, 1.1),
    # LV wall (septum, posterior wall) at end-diastole, 8-12 mm.
    "lv_wall_mm": (8.0, 12.0),
    # Apical wall relative to the basal wall: the apex is the thinnest segment.
    "lv_apex_wall_ratio": (0.6, 0.9),
    # Ellipsoid centre moved apically by this fraction of the cavity length: the base is narrower
    # than the mid-ventricle, as in the normal LV.
    "lv_base_taper": (0.1, 0.25),
    # Long axis projected on the axial plane, angle from patient left toward anterior (~45 deg).
    "axis_azimuth_deg": (30.0, 60.0),
    # Apex declination below the axial plane (the heart lies on the diaphragm, 20-40 deg).
    "axis_elevation_deg": (20.0, 40.0),
    # Rotation of the RV about the LV long axis: RV position varies by +-15 deg among subjects.
    "axis_roll_deg": (-15.0, 15.0),
    # RV apex-to-base extent relative to the LV: the LV forms the cardiac apex.
    "rv_length_ratio": (0.7, 0.85),
    # RV crescent thickness (septum to free wall, mid-ventricle): 15-28 mm (RV basal diameter 25-41 mm).
    "rv_depth_mm": (15.0, 28.0),
    # Half-width of the RV crescent around the LV: wraps ~100-140 deg of the septal circumference.
    "rv_width_mm": (45.0, 60.0),
    # LA radius (antero-posterior); with the elongation and what the vessels and the base plane
    # take, labelled LA volumes of 43-77 ml (measured, 150 seeds), inside the 40-80 ml stated below.
    "la_radius_mm": (23.5, 27.0),
    # LA left-right elongation: the LA is wider transversely than antero-posteriorly.
    "la_elongation": (1.1, 1.3),
    # RA radius; with the elongation, labelled RA volumes of 39-66 ml (measured, 150 seeds).
    "ra_radius_mm": (21.5, 24.0),
    # RA elongation along the caval (superior-inferior) direction.
    "ra_elongation": (1.05, 1.3),
    # Aortic root radius 12-18 mm (sinus of Valsalva diameter 24-36 mm).
    "aortic_root_radius_mm": (12.0, 18.0),
    # Arch radius relative to the root: the aorta tapers from the sinus to the arch.
    "aortic_taper": (0.7, 0.9),
    # Annulus to the start of the arch; ascending aorta 40-60 mm long.
    "ascending_length_mm": (40.0, 60.0),
    # Ascending aorta tilt from the vertical toward the patient's right.
    "ascending_tilt_right_deg": (5.0, 25.0),
    # Ascending aorta tilt from the vertical toward anterior.
    "ascending_tilt_anterior_deg": (-5.0, 15.0),
    # Radius of curvature of the arch centreline; arch width (2R) 45-70 mm.
    "arch_curvature_mm": (22.0, 35.0),
    # Angle swept by the arch before the (truncated) descending aorta.
    "arch_sweep_deg": (120.0, 170.0),
    # Arch plane heading from straight posterior toward the patient's left (oblique arch plane).
    "arch_azimuth_deg": (15.0, 45.0),
    # Main pulmonary artery radius 11-15 mm (diameter 22-29 mm, normal < 29 mm).
    "pa_radius_mm": (11.0, 15.0),
    # Main pulmonary trunk length, valve to bifurcation, ~40-50 mm.
    "pa_trunk_length_mm": (35.0, 50.0),
    # Trunk tilt from vertical toward posterior: the trunk runs up and back over the LA.
    "pa_pitch_deg": (30.0, 55.0),
    # Trunk heading from straight posterior toward the patient's left.
    "pa_yaw_deg": (10.0, 35.0),
    # Pulmonary valve height above the aortic valve: the RVOT lifts it ~1-2 cm.
    "pa_valve_height_mm": (8.0, 18.0),
    # Branch (LPA/RPA) radius relative to the trunk; branch diameters 15-22 mm.
    "pa_branch_ratio": (0.65, 0.8),
    # Extent of the pulmonary branches kept before truncation.
    "pa_branch_length_mm": (15.0, 30.0),
    # Branch direction below the transverse axis, toward posterior (LPA arches back over the bronchus).
    "pa_branch_angle_deg": (20.0, 45.0),
}


# Labelled volume of each structure (ml, canonical names), adult end-diastole: the ranges the
# phantom's parameters are chosen to stay within (tested over seeds).
WHOLE_HEART_VOLUMES_ML: dict[str, tuple[float, float]] = {
    # LV end-diastolic volume, CMR normal adults (women and men) ~75-200 ml.
    "lv": (75.0, 200.0),
    # LV myocardium: mass 90-210 g at 1.05 g/ml.
    "myo": (85.0, 200.0),
    # RV end-diastolic volume, CMR normal adults ~90-250 ml (the RVOT included).
    "rv": (90.0, 250.0),
    # LA maximal volume 40-80 ml (CT, appendage excluded).
    "la": (40.0, 80.0),
    # RA maximal volume 35-70 ml.
    "ra": (35.0, 70.0),
    # Aorta as truncated here (root, ascending, arch): radius 8-18 mm over 100-200 mm.
    "aorta": (30.0, 130.0),
    # Pulmonary trunk and the kept stubs of the branches.
    "pa": (10.0, 45.0),
}


def sample_uniform(ranges: dict[str, tuple[float, float]], rng: np.random.Generator) -> dict[str, float]:
    """One uniform draw per parameter, in the table's order (so the draw is reproducible)."""
    return {name: float(rng.uniform(low, high)) for name, (low, high) in ranges.items()}


def sample_whole_heart_params(rng: np.random.Generator) -> dict[str, float]:
    """Shape parameters of one whole-heart subject, drawn from `WHOLE_HEART_RANGES`."""
    return sample_uniform(WHOLE_HEART_RANGES, rng)


# ---------------------------------------------------------------------------------------------
# Frames and primitives


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def heart_axes(azimuth_deg: float, elevation_deg: float, roll_deg: float) -> np.ndarray:
    """Rows (u, v, a) of the heart frame in RAS: a along the LV long axis, base to apex (toward
    left-anterior-inferior); u toward the RV (right-anterior); v = a x u. Returns (3, 3)."""
    az, el, roll = np.radians([azimuth_deg, elevation_deg, roll_deg])
    a = np.array([-np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
    right_anterior = np.array([1.0, 1.0, 0.0])
    u0 = _unit(right_anterior - right_anterior.dot(a) * a)
    u = np.cos(roll) * u0 + np.sin(roll) * np.cross(a, u0)
    return np.stack([u, np.cross(a, u), a])


def _in_plane(direction, axis: np.ndarray) -> np.ndarray:
    """Unit projection of `direction` on the plane normal to `axis`."""
    d = np.asarray(direction, float)
    return _unit(d - d.dot(axis) * axis)


def _smooth_min(a, b, k: float):
    """Polynomial smooth minimum: a union of two signed distances with a fillet of radius ~k."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _blend(distances, k: float):
    """Smooth union of signed distances, folded left to right (the order matters slightly)."""
    result = distances[0]
    for d in distances[1:]:
        result = _smooth_min(result, d, k)
    return result


@dataclass(frozen=True)
class _Ellipsoid:
    """Ellipsoid with semi-axes `radii` along the rows of `axes`, optionally cut by a plane
    (the side where (p - cut_point) . cut_normal >= 0 is kept)."""

    centre: np.ndarray
    axes: np.ndarray
    radii: np.ndarray
    cut_point: np.ndarray | None = None
    cut_normal: np.ndarray | None = None

    def sdf(self, x, y, z):
        """Approximate signed distance (exact on the surface, good near it) at broadcastable x, y, z."""
        dx, dy, dz = x - self.centre[0], y - self.centre[1], z - self.centre[2]
        q = [e[0] * dx + e[1] * dy + e[2] * dz for e in self.axes]
        k0 = np.sqrt(sum((qi / r) ** 2 for qi, r in zip(q, self.radii)))
        k1 = np.sqrt(sum((qi / r**2) ** 2 for qi, r in zip(q, self.radii)))
        d = k0 * (k0 - 1.0) / np.maximum(k1, 1e-6)
        if self.cut_normal is None:
            return d
        p, n = self.cut_point, self.cut_normal
        return np.maximum(d, -((x - p[0]) * n[0] + (y - p[1]) * n[1] + (z - p[2]) * n[2]))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        half = np.sqrt(((self.axes * self.radii[:, None]) ** 2).sum(axis=0))
        return self.centre - half, self.centre + half


@dataclass(frozen=True)
class _Segment:
    start: np.ndarray
    direction: np.ndarray
    length: float

    def nearest(self, dx, dy, dz):
        """Arclength of the nearest point to offsets (dx, dy, dz) from `start`, and that point's offsets."""
        d = self.direction
        s = np.clip(dx * d[0] + dy * d[1] + dz * d[2], 0.0, self.length)
        return s, (s * d[0], s * d[1], s * d[2])

    def point(self, s):
        return self.start + np.multiply.outer(s, self.direction)

    def tangent(self, s):
        return self.direction

    def trimmed(self, length: float) -> _Segment:
        return _Segment(self.start, self.direction, length)


@dataclass(frozen=True)
class _Arc:
    """Circular arc from `start` with initial tangent `tangent0`, bending toward `bend` (unit,
    normal to the tangent) with curvature radius `radius`, over `sweep` radians."""

    start: np.ndarray
    tangent0: np.ndarray
    bend: np.ndarray
    radius: float
    sweep: float

    @property
    def length(self) -> float:
        return self.radius * self.sweep

    def nearest(self, dx, dy, dz):
        # Offsets from the circle's centre, in the arc's plane basis (-bend, tangent0).
        r, t, b = self.radius, self.tangent0, self.bend
        cx, cy, cz = dx - r * b[0], dy - r * b[1], dz - r * b[2]
        along_t = cx * t[0] + cy * t[1] + cz * t[2]
        along_b = -(cx * b[0] + cy * b[1] + cz * b[2])
        phi = np.mod(np.arctan2(along_t, along_b), 2 * np.pi)
        # Angles beyond the sweep snap to the nearer end of the arc.
        past_end = phi > self.sweep
        phi = np.where(past_end & (phi - self.sweep < 2 * np.pi - phi), self.sweep, np.where(past_end, 0.0, phi))
        c, s = np.cos(phi), np.sin(phi)
        return r * phi, tuple(r * b[i] + r * (s * t[i] - c * b[i]) for i in range(3))

    def point(self, s):
        phi = np.asarray(s) / self.radius
        return self.start + self.radius * (
            np.multiply.outer(np.sin(phi), self.tangent0) + np.multiply.outer(1.0 - np.cos(phi), self.bend)
        )

    def tangent(self, s):
        phi = s / self.radius
        return np.cos(phi) * self.tangent0 + np.sin(phi) * self.bend

    def trimmed(self, length: float) -> _Arc:
        return _Arc(self.start, self.tangent0, self.bend, self.radius, length / self.radius)


@dataclass(frozen=True)
class _Tube:
    """Tube along a tangent-continuous chain of pieces (segments, arcs); radius linear in
    arclength from `radius0` to `radius1` over the untrimmed length `taper_length`. A cut end is
    flat (a truncated vessel), an uncut one rounded (a junction)."""

    pieces: tuple
    radius0: float
    radius1: float
    taper_length: float
    cut_end: bool = True

    @property
    def length(self) -> float:
        return sum(p.length for p in self.pieces)

    def radius(self, s):
        return self.radius0 + (self.radius1 - self.radius0) * np.clip(s / self.taper_length, 0.0, 1.0)

    def end(self) -> tuple[np.ndarray, np.ndarray]:
        last = self.pieces[-1]
        return last.point(last.length), last.tangent(last.length)

    def sdf(self, x, y, z):
        best = None
        offset = 0.0
        for piece in self.pieces:
            p0 = piece.start
            dx, dy, dz = x - p0[0], y - p0[1], z - p0[2]
            s, (nx, ny, nz) = piece.nearest(dx, dy, dz)
            d = np.sqrt((dx - nx) ** 2 + (dy - ny) ** 2 + (dz - nz) ** 2) - self.radius(offset + s)
            if self.cut_end and piece is self.pieces[-1]:
                # Flat cap: where the nearest centreline point is the end, nothing lies beyond
                # the plane through the end point normal to the end tangent.
                p, t = self.end()
                beyond = (x - p[0]) * t[0] + (y - p[1]) * t[1] + (z - p[2]) * t[2]
                d = np.where(s >= piece.length, np.maximum(d, beyond), d)
            best = d if best is None else np.minimum(best, d)
            offset += piece.length
        return best

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """Centreline points (N, 3) every ~`_CURVE_STEP_MM` and the arclength (N,) of each."""
        points, arclengths, offset = [], [], 0.0
        for piece in self.pieces:
            s = np.linspace(0.0, piece.length, max(2, int(np.ceil(piece.length / _CURVE_STEP_MM)) + 1))
            points.append(piece.point(s))
            arclengths.append(offset + s)
            offset += piece.length
        return np.concatenate(points), np.concatenate(arclengths)

    def trimmed(self, length: float) -> _Tube:
        """The same tube cut (flat) at arclength `length`."""
        kept, offset = [], 0.0
        for piece in self.pieces:
            if offset + piece.length >= length:
                kept.append(piece.trimmed(length - offset))
                break
            kept.append(piece)
            offset += piece.length
        return _Tube(tuple(kept), self.radius0, self.radius1, self.taper_length, cut_end=True)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        points, _ = self.samples()
        pad = max(self.radius0, self.radius1)
        return points.min(axis=0) - pad, points.max(axis=0) + pad


@dataclass(frozen=True)
class _SmoothUnion:
    parts: tuple
    blend_mm: float

    def sdf(self, x, y, z):
        return _blend([part.sdf(x, y, z) for part in self.parts], self.blend_mm)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lows, highs = zip(*(p.bounds() for p in self.parts))
        return np.min(lows, axis=0), np.max(highs, axis=0)


def _at_points(shape, points: np.ndarray) -> np.ndarray:
    """Signed distance of `shape` at points (N, 3)."""
    return shape.sdf(points[:, 0], points[:, 1], points[:, 2])


def _on_grid(shape, axes: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """Signed distance (X, Y, Z) float32 of `shape` on the grid of voxel-centre coordinates `axes`,
    evaluated only inside its padded bounding box and clamped to `_FAR_MM` (outside it)."""
    lo, hi = shape.bounds()
    out = np.full(tuple(len(a) for a in axes), _FAR_MM, np.float32)
    box = tuple(slice(np.searchsorted(a, l - _FAR_MM), np.searchsorted(a, h + _FAR_MM)) for a, l, h in zip(axes, lo, hi))
    x, y, z = (a[s].astype(np.float32) for a, s in zip(axes, box))
    out[box] = np.minimum(shape.sdf(x[:, None, None], y[None, :, None], z[None, None, :]), _FAR_MM)
    return out


def _cut_on_return(tube: _Tube, obstacle) -> _Tube:
    """The tube cut where, once outside `obstacle`, it turns back toward it within
    `_VESSEL_GAP_MM`: a vessel leaves the body once and never touches it again (no handle).

    Turning back means a clearance below both the gap and the largest clearance reached so far
    (less `_RETURN_TOLERANCE_MM`). A branch that starts at the fork nearer than the gap and
    runs on toward the body is cut too, not only a vessel that cleared the gap first."""
    points, arclength = tube.samples()
    clearance = _at_points(obstacle, points) - tube.radius(arclength)
    reached = np.maximum.accumulate(clearance)
    back = (reached > 0) & (clearance < np.minimum(_VESSEL_GAP_MM, reached - _RETURN_TOLERANCE_MM))
    if not back.any():
        return tube
    return tube.trimmed(float(arclength[int(np.argmax(back))]))


@dataclass(frozen=True)
class _Min:
    """Plain union of signed distances (no fillet)."""

    parts: tuple

    def sdf(self, x, y, z):
        result = self.parts[0].sdf(x, y, z)
        for part in self.parts[1:]:
            result = np.minimum(result, part.sdf(x, y, z))
        return result

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lows, highs = zip(*(p.bounds() for p in self.parts))
        return np.min(lows, axis=0), np.max(highs, axis=0)


# ---------------------------------------------------------------------------------------------
# Whole heart (MM-WHS)

# Label precedence where primitives overlap: the LV (cavity, then wall) keeps the septum and the
# mitral plane, the RV keeps its outflow tract, vessels indent the atria they run beside.
_WHOLE_HEART_PRECEDENCE = (LV_BLOOD, LV_MYO, RV, AORTA, PULMONARY_ARTERY, LA, RA)
# The chambers, in the order they are smooth-unioned into the body.
_CHAMBER_ORDER = (LV_MYO, RV, LA, RA)


def _whole_heart_shapes(params: dict) -> tuple[dict[int, object], object]:
    """The structures of one whole heart in RAS mm around the LV base centre (the origin).

    Returns label code -> shape (with `sdf(x, y, z)` and `bounds()`), and the unlabelled
    atrioventricular plate. The LV_MYO shape is the whole epicardial solid (wall and cavity);
    LV_BLOOD is the cavity inside it. The chamber body is `_CHAMBER_ORDER` then the plate,
    smooth-unioned in that order."""
    p = params
    axes = heart_axes(p["axis_azimuth_deg"], p["axis_elevation_deg"], p["axis_roll_deg"])
    u, a = axes[0], axes[2]
    base = np.zeros(3)
    # Base-plane directions toward the patient's superior and posterior.
    superior = _in_plane([0.0, 0.0, 1.0], a)
    posterior = _in_plane([0.0, -1.0, 0.0], a)

    # LV: cavity and epicardium share a centre moved apically (base narrower than mid-cavity),
    # both cut at the base plane.
    wall = p["lv_wall_mm"]
    apex_wall = wall * p["lv_apex_wall_ratio"]
    cavity_length = p["lv_length_mm"] - apex_wall
    shift = p["lv_base_taper"] * cavity_length
    lv_centre = base + shift * a
    r_cav = p["lv_cavity_radius_mm"]
    cavity_radii = np.array([r_cav, r_cav * p["lv_cavity_ellipticity"], cavity_length - shift])
    cavity = _Ellipsoid(lv_centre, axes, cavity_radii, base, a)
    epicardium = _Ellipsoid(lv_centre, axes, cavity_radii + [wall, wall, apex_wall], base, a)
    r_epi = r_cav + wall

    # RV: an ellipsoid whose septal side lies inside the LV, so that what the LV leaves of it is
    # a crescent of thickness `rv_depth_mm` over the septum; its outflow tract (RVOT) is a tube
    # from the RV body to the pulmonary valve.
    septal_edge, free_wall = 0.3 * r_epi, r_epi + p["rv_depth_mm"]
    rv_length = p["rv_length_ratio"] * p["lv_length_mm"]
    rv_centre = base + 0.5 * (septal_edge + free_wall) * u + 0.2 * rv_length * a
    rv_radii = np.array([0.5 * (free_wall - septal_edge), p["rv_width_mm"], 0.8 * rv_length])
    rv_body = _Ellipsoid(rv_centre, axes, rv_radii, base, a)

    # Atria sit on the base plane (cut by it) on the far side from the apex: the LA over the
    # mitral valve toward posterior-left, the RA over the tricuspid valve (RV base) on the right.
    r_la = p["la_radius_mm"]
    la_radii = np.array([r_la * p["la_elongation"], r_la, 0.85 * r_la])
    la_centre = base + 0.3 * r_cav * posterior - 0.6 * la_radii[2] * a
    la = _Ellipsoid(la_centre, axes, la_radii, base, -a)
    r_ra = p["ra_radius_mm"]
    ra_axes = np.stack([u, np.cross(superior, u), superior])
    ra_radii = np.array([r_ra, r_ra, r_ra * p["ra_elongation"]])
    # The atria share the interatrial septum: the RA centre lies toward the tricuspid valve at
    # 80 % of the two radii from the LA centre, so that they always overlap (two atria that only
    # nearly touched would close a ring with the base).
    tricuspid = (r_epi + 0.5 * p["rv_depth_mm"]) * u
    toward_tricuspid = _in_plane(tricuspid - la_centre, a)
    la_in_base_plane = la_centre - la_centre.dot(a) * a
    ra_centre = la_in_base_plane + 0.8 * (la_radii[0] + r_ra) * toward_tricuspid - 0.6 * r_ra * a
    ra = _Ellipsoid(ra_centre, ra_axes, ra_radii, base, -a)

    # Aorta: from the LV outflow (anterior-superior part of the base, toward the septum) up the
    # ascending segment, then the arch bending toward posterior-left.
    r_ao = p["aortic_root_radius_mm"]
    ao_root = base + 0.45 * r_cav * superior + 0.3 * r_cav * u + 3.0 * a
    tilt_r, tilt_a = np.radians([p["ascending_tilt_right_deg"], p["ascending_tilt_anterior_deg"]])
    ascending_dir = _unit([np.tan(tilt_r), np.tan(tilt_a), 1.0])
    ascending = _Segment(ao_root, ascending_dir, p["ascending_length_mm"])
    arch_az = np.radians(p["arch_azimuth_deg"])
    arch_bend = _in_plane([-np.sin(arch_az), -np.cos(arch_az), 0.0], ascending_dir)
    arch = _Arc(ascending.point(ascending.length), ascending_dir, arch_bend, p["arch_curvature_mm"],
                np.radians(p["arch_sweep_deg"]))
    aorta_length = ascending.length + arch.length
    aorta = _Tube((ascending, arch), r_ao, r_ao * p["aortic_taper"], aorta_length)

    # Pulmonary valve: left-anterior of the aortic root, clear of it by the vessel gap, and higher.
    r_pa = p["pa_radius_mm"]
    left_anterior = _unit([-1.0, 1.0, 0.0])
    valve = ao_root + (r_ao + r_pa + _VESSEL_GAP_MM + 2.0) * left_anterior + p["pa_valve_height_mm"] * np.array([0, 0, 1.0])
    rvot_start = rv_centre + 0.2 * rv_length * a
    rvot = _Tube((_Segment(rvot_start, _unit(valve - rvot_start), float(np.linalg.norm(valve - rvot_start))),),
                 r_pa, r_pa, 1.0, cut_end=False)
    rv = _SmoothUnion((rv_body, rvot), _CHAMBER_BLEND_MM)

    # Atrioventricular plate (fibrous skeleton and AV-groove fat): a flat ellipsoid across the
    # base plane under all four chambers. Without it the ring LV-LA-RA-RV can enclose a tunnel
    # at the crux; with it the four meet over one contiguous region.
    plate = _Ellipsoid(base + 0.5 * tricuspid, axes, np.array([0.5 * np.linalg.norm(tricuspid) + r_cav, r_cav, 8.0]))
    chamber_shapes = {LV_MYO: epicardium, RV: rv, LA: la, RA: ra}
    chambers = _SmoothUnion((*(chamber_shapes[code] for code in _CHAMBER_ORDER), plate), _CHAMBER_BLEND_MM)
    aorta = _cut_on_return(aorta, chambers)

    # Pulmonary trunk from the valve, up and back (posterior-superior, leftward), then the two
    # branches; each part is cut where it would come back to the body or meet the aorta.
    pitch, yaw = np.radians([p["pa_pitch_deg"], p["pa_yaw_deg"]])
    trunk_dir = np.array([-np.sin(yaw) * np.sin(pitch), -np.cos(yaw) * np.sin(pitch), np.cos(pitch)])
    r_branch = r_pa * p["pa_branch_ratio"]
    trunk = _Tube((_Segment(valve, trunk_dir, p["pa_trunk_length_mm"]),), r_pa, r_branch, p["pa_trunk_length_mm"],
                  cut_end=False)
    obstacle = _Min((chambers, aorta))
    cut_trunk = _cut_on_return(trunk, obstacle)
    pulmonary = [cut_trunk]
    if cut_trunk is trunk:
        fork, _ = trunk.end()
        beta = np.radians(p["pa_branch_angle_deg"])
        for side in (-1.0, 1.0):
            direction = _unit([side * np.cos(beta), -np.sin(beta), -0.15])
            branch = _Tube((_Segment(fork, direction, p["pa_branch_length_mm"]),), r_branch, r_branch, 1.0)
            pulmonary.append(_cut_on_return(branch, obstacle))
    pa = pulmonary[0] if len(pulmonary) == 1 else _Min(tuple(pulmonary))
    return {LV_BLOOD: cavity, LV_MYO: epicardium, RV: rv, AORTA: aorta, PULMONARY_ARTERY: pa, LA: la, RA: ra}, plate


def whole_heart_labels(params: dict, voxel_mm=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Label map of one whole heart.

    Parameters
    ----------
    params : dict from `sample_whole_heart_params`.
    voxel_mm : voxel size (3,) in mm.

    Returns
    -------
    labels : (X, Y, Z) uint16, MM-WHS codes, 0 outside the heart. Stored as CT often is: voxel
        axes 0 and 1 run toward patient left and posterior (LPS-like), axis 2 toward superior.
    affine : (4, 4) float64, voxel index -> RAS mm.
    """
    spacing = np.asarray(voxel_mm, float)
    shapes, plate = _whole_heart_shapes(params)
    lows, highs = zip(*(shape.bounds() for shape in shapes.values()))
    margin = _CHAMBER_BLEND_MM + 3 * spacing
    lo, hi = np.min(lows, axis=0) - margin, np.max(highs, axis=0) + margin
    counts = np.ceil((hi - lo) / spacing).astype(int) + 1
    axes = tuple(lo[i] + spacing[i] * np.arange(counts[i]) for i in range(3))

    fields = {code: _on_grid(shape, axes) for code, shape in shapes.items()}
    body = _blend([*(fields[code] for code in _CHAMBER_ORDER), _on_grid(plate, axes)], _CHAMBER_BLEND_MM)
    solid = np.minimum(_smooth_min(body, fields[AORTA], _VESSEL_BLEND_MM),
                       _smooth_min(body, fields[PULMONARY_ARTERY], _VESSEL_BLEND_MM))
    del body

    # Fillet voxels (inside the blended solid, outside every primitive) take the nearest
    # structure; the LV wall stands for the whole LV there, since fillets lie outside it.
    outer_codes = [c for c in _WHOLE_HEART_PRECEDENCE if c != LV_BLOOD]
    nearest = np.asarray(outer_codes, np.uint16)[np.argmin(np.stack([fields[c] for c in outer_codes]), axis=0)]
    labels = np.where(solid < 0, nearest, 0).astype(np.uint16)
    for code in reversed(_WHOLE_HEART_PRECEDENCE):
        labels[fields[code] < 0] = code
    # The LV blood pool never touches the right heart: where the base plane brings it against the
    # RA, RV or PA, a rim of myocardium (the AV septum) closes it. Elsewhere on the base it stays
    # open, as in MM-WHS, whose myocardium label stops at the valve plane.
    right_heart = ndimage.binary_dilation(np.isin(labels, (RA, RV, PULMONARY_ARTERY)))
    labels[right_heart & (labels == LV_BLOOD)] = LV_MYO

    # Store LPS-like: flip the first two voxel axes, as DICOM-derived CT volumes usually are.
    affine = np.diag([-spacing[0], -spacing[1], spacing[2], 1.0])
    affine[:3, 3] = [axes[0][-1], axes[1][-1], axes[2][0]]
    return np.ascontiguousarray(labels[::-1, ::-1, :]), affine


def write_mmwhs_subject(folder: Path, subject_id: str, rng: np.random.Generator, voxel_mm=(1.0, 1.0, 1.0)) -> Path:
    """Draw one whole heart and write `<folder>/<subject_id>_label.nii.gz` (MM-WHS layout,
    e.g. subject_id "ct_train_1001"); byte-identical for the same generator state."""
    labels, affine = whole_heart_labels(sample_whole_heart_params(rng), voxel_mm)
    path = Path(folder) / f"{subject_id}_label.nii.gz"
    write_bytes(path, nifti_gz_bytes(labels, affine))
    return path


def nifti_gz_bytes(data: np.ndarray, affine: np.ndarray) -> bytes:
    """A .nii.gz file's bytes, reproducible: gzip stores mtime 0 and no file name."""
    image = nib.Nifti1Image(data, affine)
    image.header.set_xyzt_units("mm", "sec")
    image.set_qform(affine, code=1)
    image.set_sform(affine, code=1)
    return gzip.compress(image.to_bytes(), compresslevel=6, mtime=0)

