"""Built-in parametric phantoms: a seeded whole heart (MM-WHS labels) and a beating biventricular heart (ACDC labels).

Both are built from smooth primitives evaluated vectorised on the voxel grid and written as
NIfTI in the layouts of the real data sets, so that the real-data loaders read them unchanged.

Whole heart. Signed-distance ellipsoids (ventricles, atria) and tubes along smooth curves
(aorta, pulmonary artery) are placed in RAS+ millimetres around the LV base centre. The
chambers and an unlabelled atrioventricular plate are smooth-unioned into one body; each vessel is smooth-unioned with that body only
(never with the other vessel), and is cut off where, having left the body, it would come back
within `_VESSEL_GAP_MM` of it or of the aorta. So the union of all labels is one solid without
handles (genus 0). Labels follow a fixed precedence; voxels of the blending fillets take the
label of the nearest structure.

Biventricular. Truncated prolate spheroids (LV cavity, epicardium) and a crescent RV on an
ACDC-like short-axis stack whose slice normal is the LV long axis. The LV cavity volume follows
a periodic curve (ejection, rapid filling, diastasis, atrial kick); the myocardial volume is held
constant, so the wall thickens as the cavity empties; the RV is resized per frame, by bisection
on its voxel count, to follow the same curve with its own ejection fraction.
"""

from __future__ import annotations

import gzip
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import nibabel as nib
import numpy as np
from scipy import ndimage

# MM-WHS label codes.
LV_MYO, LA, LV_BLOOD, RA, RV, AORTA, PULMONARY_ARTERY = 205, 420, 500, 550, 600, 820, 850
# ACDC label codes.
ACDC_BACKGROUND, ACDC_RV, ACDC_MYO, ACDC_LV = 0, 1, 2, 3

# Smooth-union radius between chambers: fills the crevices between them, as epicardial fat does.
_CHAMBER_BLEND_MM = 6.0
# Smooth-union radius between a vessel and the chamber body: a fillet at the vessel's root, wide
# enough to fill the pockets where a vessel root grazes two chambers at once (else a tunnel).
_VESSEL_BLEND_MM = 8.0
# A vessel that has left the body stays this far from it and from the other vessel. It must exceed
# half the vessel blend (else the fillet bridges the gap) and survive the meshing stage's 1 mm
# Gaussian smoothing and a 2x downsampling of the mask.
_VESSEL_GAP_MM = 7.0
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
    # LA equivalent radius; LA volume 40-80 ml (indexed 16-34 ml/m2) gives radii 21-27 mm.
    "la_radius_mm": (20.0, 26.0),
    # LA left-right elongation: the LA is wider transversely than antero-posteriorly.
    "la_elongation": (1.0, 1.3),
    # RA equivalent radius; RA volume 35-70 ml.
    "ra_radius_mm": (20.0, 26.0),
    # RA elongation along the caval (superior-inferior) direction.
    "ra_elongation": (1.0, 1.35),
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

# Biventricular (beating) parameters: name -> (low, high), drawn uniformly. Normal adults.
BIVENTRICULAR_RANGES: dict[str, tuple[float, float]] = {
    # LV end-diastolic volume; CMR normal adults ~100-160 ml.
    "lv_edv_ml": (100.0, 160.0),
    # LV ejection fraction; normal 50-65 %.
    "lv_ef": (0.50, 0.65),
    # Base to endocardial apex at end-diastole.
    "lv_cavity_length_mm": (75.0, 95.0),
    # End-diastolic wall; CMR normal 7-11 mm.
    "lv_wall_mm": (7.0, 11.0),
    # Apical wall relative to the lateral wall.
    "lv_apex_wall_ratio": (0.6, 0.9),
    # Cavity length scales as volume**exponent: 0.15-0.3 gives 10-20 % long-axis shortening.
    "long_axis_exponent": (0.15, 0.3),
    # End-systole as a fraction of the cycle (ejection ~ 300-350 ms of ~ 900 ms).
    "es_fraction": (0.30, 0.40),
    # Rapid-filling duration as a fraction of the cycle (~ 100-180 ms).
    "rapid_filling_fraction": (0.12, 0.2),
    # Share of the stroke volume refilled in early (E) filling; E/A 1-2.5 in normal adults.
    "early_filling_share": (0.6, 0.75),
    # Share refilled during diastasis.
    "diastasis_share": (0.03, 0.1),
    # Atrial contraction onset (P wave + ~100 ms), fraction of the cycle.
    "atrial_onset_fraction": (0.80, 0.87),
    # RV ejection fraction; CMR normal 45-60 %.
    "rv_ef": (0.45, 0.60),
    # RV stroke volume over LV stroke volume; equal without shunt or regurgitation.
    "rv_sv_ratio": (0.95, 1.05),
    # RV crescent half-width around the LV, relative to the LV epicardial radius.
    "rv_width_ratio": (1.2, 1.6),
    # RV apex-to-base extent relative to the LV cavity length.
    "rv_length_ratio": (0.7, 0.85),
    # Long-axis orientation (as for the whole heart): the short-axis stack is planned on it.
    "axis_azimuth_deg": (30.0, 60.0),
    "axis_elevation_deg": (20.0, 40.0),
    "axis_roll_deg": (-15.0, 15.0),
    # Subject metadata written to Info.cfg (ACDC: height in cm, weight in kg).
    "height_cm": (155.0, 190.0),
    "weight_kg": (50.0, 95.0),
}


def _sample(ranges: dict[str, tuple[float, float]], rng: np.random.Generator) -> dict[str, float]:
    """One uniform draw per parameter, in the table's order (so the draw is reproducible)."""
    return {name: float(rng.uniform(low, high)) for name, (low, high) in ranges.items()}


def sample_whole_heart_params(rng: np.random.Generator) -> dict[str, float]:
    """Shape parameters of one whole-heart subject, drawn from `WHOLE_HEART_RANGES`."""
    return _sample(WHOLE_HEART_RANGES, rng)


def sample_biventricular_params(rng: np.random.Generator) -> dict[str, float]:
    """Parameters of one beating biventricular subject, drawn from `BIVENTRICULAR_RANGES`."""
    return _sample(BIVENTRICULAR_RANGES, rng)


# ---------------------------------------------------------------------------------------------
# Frames and primitives


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _heart_axes(azimuth_deg: float, elevation_deg: float, roll_deg: float) -> np.ndarray:
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
    """The tube cut where, after first clearing `obstacle` by `_VESSEL_GAP_MM`, it comes back
    closer than that: a vessel leaves the body once and never touches it again (no handle)."""
    points, arclength = tube.samples()
    clearance = _at_points(obstacle, points) - tube.radius(arclength)
    clear = clearance > _VESSEL_GAP_MM
    if not clear.any():
        return tube
    exit_index = int(np.argmax(clear))
    back = ~clear[exit_index:]
    if not back.any():
        return tube
    return tube.trimmed(float(arclength[exit_index + int(np.argmax(back))]))


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
    axes = _heart_axes(p["axis_azimuth_deg"], p["axis_elevation_deg"], p["axis_roll_deg"])
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
    _write_atomic(path, _nifti_gz_bytes(labels, affine))
    return path


def _nifti_gz_bytes(data: np.ndarray, affine: np.ndarray) -> bytes:
    """A .nii.gz file's bytes, reproducible: gzip stores mtime 0 and no file name."""
    image = nib.Nifti1Image(data, affine)
    image.header.set_xyzt_units("mm", "sec")
    image.set_qform(affine, code=1)
    image.set_sform(affine, code=1)
    return gzip.compress(image.to_bytes(), compresslevel=6, mtime=0)


def _write_atomic(path: Path, payload: bytes) -> None:
    """Write to a temporary name beside `path`, then rename: a crash never leaves half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# ---------------------------------------------------------------------------------------------
# Beating biventricular heart (ACDC)

# Empty slices above the base (the atria in real ACDC stacks) and below the apex.
_SLICES_ABOVE_BASE = 1
_SLICES_BELOW_APEX = 1
# Anchor of the RV's septal edge inside the LV, beyond its axis, as a fraction of the smallest
# epicardial radius: the RV ellipsoid is centred near the LV axis, so what the LV leaves of it
# is a crescent wrapping the septum, and it never reaches round behind the LV.
_RV_SEPTAL_ANCHOR = -0.5
# End-diastolic RV crescent thickness before resizing to the target volume (mm).
_RV_NOMINAL_DEPTH_MM = 20.0


def _ease(x):
    """Half-cosine ramp from 0 (x <= 0) to 1 (x >= 1), flat at both ends."""
    return 0.5 * (1.0 - np.cos(np.pi * np.clip(x, 0.0, 1.0)))


def _lv_volume_curve(t: np.ndarray, params: dict) -> np.ndarray:
    """LV cavity volume over end-diastolic volume (T,) at cycle fractions t (T,) in [0, 1):
    ejection to end-systole, rapid filling, diastasis, atrial kick; periodic, with zero slope at
    end-diastole (t = 0) and end-systole, where it is 1 and 1 - EF."""
    p = params
    ef, t_es = p["lv_ef"], p["es_fraction"]
    t_rapid_end = t_es + p["rapid_filling_fraction"]
    t_atrial = p["atrial_onset_fraction"]
    early, diastasis = p["early_filling_share"], p["diastasis_share"]
    refilled = (early * _ease((t - t_es) / (t_rapid_end - t_es))
                + diastasis * _ease((t - t_rapid_end) / (t_atrial - t_rapid_end))
                + (1.0 - early - diastasis) * _ease((t - t_atrial) / (1.0 - t_atrial)))
    return np.where(t < t_es, 1.0 - ef * _ease(t / t_es), 1.0 - ef + ef * refilled)


def _half_spheroid(x, y, z, radius, length):
    """Inside (bool) of the half prolate spheroid {x^2 + y^2 <= r^2 (1 - (z/L)^2), 0 <= z}."""
    return (z >= 0.0) & ((x * x + y * y) / radius**2 + (z / length) ** 2 <= 1.0)


def biventricular_frames(params: dict, n_frames: int = 20, voxel_mm=(1.5, 1.5, 8.0)) -> tuple[list[np.ndarray], np.ndarray, dict]:
    """Label maps of one beating biventricular heart over one cycle, ED first.

    The LV cavity is a half prolate spheroid on the base plane (r, L); the epicardium another
    (R, L + apex wall) holding the myocardial volume constant; the base plane stays on a slice
    boundary, so voxel counts measure volumes without whole-slice jumps, and long-axis
    shortening draws the apex toward the base. The RV is an ellipsoid anchored inside the LV,
    beyond its axis (so the LV leaves a crescent of it), scaled per frame (bisection on its voxel count) to its target volume.

    Parameters
    ----------
    params : dict from `sample_biventricular_params`.
    n_frames : frames T over the cycle (frame 1 at end-diastole).
    voxel_mm : voxel size (3,); the third axis is the slice axis (short-axis stack).

    Returns
    -------
    frames : list of T label maps (X, Y, Z) uint8, ACDC codes (0 bg, 1 RV, 2 myo, 3 LV).
    affine : (4, 4) float64, voxel index -> RAS mm; the slice normal is the LV long axis.
    info : dict with ed_frame, es_frame (1-based, ES at the smallest measured LV volume),
        lv_volume_ml, rv_volume_ml, myo_volume_ml (T,) lists measured from voxel counts,
        ef and rv_ef (measured), height_cm, weight_kg.
    """
    p = params
    spacing = np.asarray(voxel_mm, float)
    voxel_ml = float(np.prod(spacing)) / 1000.0
    volume = _lv_volume_curve(np.arange(n_frames) / n_frames, p)

    # LV geometry per frame: cavity (r, L) from its volume and long-axis shortening; epicardium
    # from the constant myocardial volume.
    cavity_ml = p["lv_edv_ml"] * volume
    cavity_length = p["lv_cavity_length_mm"] * volume ** p["long_axis_exponent"]
    cavity_radius = np.sqrt(1000.0 * cavity_ml / (2.0 / 3.0 * np.pi * cavity_length))
    apex_wall = p["lv_wall_mm"] * p["lv_apex_wall_ratio"]
    epi_length = cavity_length + apex_wall
    epi_radius_ed = cavity_radius[0] + p["lv_wall_mm"]
    myo_volume = 2.0 / 3.0 * np.pi * (epi_radius_ed**2 * epi_length[0] - cavity_radius[0] ** 2 * cavity_length[0])
    epi_radius = np.sqrt((1.5 * myo_volume / np.pi + cavity_radius**2 * cavity_length) / epi_length)

    # Grid: voxel centres in the heart frame (x toward the RV, z from the base toward the apex).
    half_width = 2.0 * epi_radius_ed + 25.0
    n_xy = [int(np.ceil(2.0 * half_width / s)) for s in spacing[:2]]
    n_z = _SLICES_ABOVE_BASE + int(np.ceil(epi_length[0] / spacing[2])) + _SLICES_BELOW_APEX
    x_shift = -0.4 * epi_radius_ed  # LV left of centre, so the RV fits in the field of view
    first = np.array([x_shift - (n_xy[0] - 1) / 2 * spacing[0], -(n_xy[1] - 1) / 2 * spacing[1],
                      (0.5 - _SLICES_ABOVE_BASE) * spacing[2]])
    x = (first[0] + spacing[0] * np.arange(n_xy[0]))[:, None, None]
    y = (first[1] + spacing[1] * np.arange(n_xy[1]))[None, :, None]
    z = (first[2] + spacing[2] * np.arange(n_z))[None, None, :]

    # RV: ellipsoid (depth, width, length) = kappa * (r_u, r_w, r_l) (length as kappa**exponent),
    # its septal edge pinned at x = anchor, cut at the base plane.
    anchor = _RV_SEPTAL_ANCHOR * float(epi_radius.min())
    rv_axes = np.array([0.5 * (epi_radius_ed + _RV_NOMINAL_DEPTH_MM - anchor),
                        p["rv_width_ratio"] * epi_radius_ed, p["rv_length_ratio"] * p["lv_cavity_length_mm"]])

    def rv_mask(kappa: float, epicardium: np.ndarray) -> np.ndarray:
        depth, width, length = kappa * rv_axes[0], kappa * rv_axes[1], kappa ** p["long_axis_exponent"] * rv_axes[2]
        inside = (((x - anchor - depth) / depth) ** 2 + (y / width) ** 2 + (z / length) ** 2 <= 1.0) & (z >= 0.0)
        return inside & ~epicardium

    lv_sv_ml = p["lv_edv_ml"] * p["lv_ef"]
    rv_edv_ml = p["rv_sv_ratio"] * lv_sv_ml / p["rv_ef"]
    rv_target_ml = rv_edv_ml * (1.0 - p["rv_ef"] * (1.0 - volume) / p["lv_ef"])

    frames = []
    for i in range(n_frames):
        cavity = _half_spheroid(x, y, z, cavity_radius[i], cavity_length[i])
        epicardium = _half_spheroid(x, y, z, epi_radius[i], epi_length[i])
        # Smallest kappa whose RV holds the target: bisection on the (monotone) voxel count.
        low, high = 0.2, 3.0
        for _ in range(30):
            mid = 0.5 * (low + high)
            if np.count_nonzero(rv_mask(mid, epicardium)) * voxel_ml < rv_target_ml[i]:
                low = mid
            else:
                high = mid
        labels = np.zeros((n_xy[0], n_xy[1], n_z), np.uint8)
        labels[rv_mask(high, epicardium)] = ACDC_RV
        labels[epicardium] = ACDC_MYO
        labels[cavity] = ACDC_LV
        frames.append(labels)

    axes = _heart_axes(p["axis_azimuth_deg"], p["axis_elevation_deg"], p["axis_roll_deg"])
    affine = np.eye(4)
    affine[:3, :3] = axes.T * spacing
    affine[:3, 3] = axes.T @ first

    counts = {code: np.array([np.count_nonzero(f == code) for f in frames]) * voxel_ml for code in (ACDC_LV, ACDC_MYO, ACDC_RV)}
    lv, rv = counts[ACDC_LV], counts[ACDC_RV]
    es = int(np.argmin(lv))
    info = {
        "ed_frame": 1,
        "es_frame": es + 1,
        "lv_volume_ml": lv.tolist(),
        "rv_volume_ml": rv.tolist(),
        "myo_volume_ml": counts[ACDC_MYO].tolist(),
        "ef": float(1.0 - lv[es] / lv[0]),
        "rv_ef": float(1.0 - rv.min() / rv[0]),
        "height_cm": round(p["height_cm"], 1),
        "weight_kg": round(p["weight_kg"], 1),
    }
    return frames, affine, info


def write_acdc_subject(folder: Path, patient_id: str, rng: np.random.Generator, n_frames: int = 20,
                       voxel_mm=(1.5, 1.5, 8.0)) -> Path:
    """Draw one beating heart and write it in the ACDC layout: `<folder>/<patient_id>/Info.cfg`
    and `<patient_id>_frameYY_gt.nii.gz` for every frame YY = 01..T (e.g. patient_id
    "patient001"). Returns the patient folder. Byte-identical for the same generator state."""
    frames, affine, info = biventricular_frames(sample_biventricular_params(rng), n_frames, voxel_mm)
    subject = Path(folder) / patient_id
    for index, labels in enumerate(frames, start=1):
        _write_atomic(subject / f"{patient_id}_frame{index:02d}_gt.nii.gz", _nifti_gz_bytes(labels, affine))
    # Group NOR: the sampled ranges are those of normal subjects.
    cfg = (f"ED: {info['ed_frame']}\nES: {info['es_frame']}\nGroup: NOR\nHeight: {info['height_cm']:.1f}\n"
           f"NbFrame: {n_frames}\nWeight: {info['weight_kg']:.1f}\n")
    _write_atomic(subject / "Info.cfg", cfg.encode("ascii"))
    return subject
