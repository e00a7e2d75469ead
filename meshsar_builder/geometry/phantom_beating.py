"""Built-in beating biventricular phantom (ACDC layout), seeded and parametric.

Truncated prolate spheroids (LV cavity, epicardium) and a crescent RV on an ACDC-like short-axis
stack whose slice normal is the LV long axis. The LV cavity volume follows a periodic curve
(ejection, rapid filling, diastasis, atrial kick); the myocardial volume is held constant, so the
wall thickens as the cavity empties; the RV is resized per frame, by bisection on its voxel
count, to follow the same curve with its own ejection fraction. The heart moves as real ones do:
the apex stays put while the atrioventricular (base) plane descends toward it in systole, and the
ventricles twist (apex counter-clockwise, base clockwise, seen from the apex). The stack follows
the base plane (as slice tracking does), so each frame has its own affine. Frames are written as
NIfTI in the ACDC layout, so the real-data loader reads them unchanged.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from meshsar_builder.geometry.phantom_heart import heart_axes, nifti_gz_bytes, sample_uniform
from meshsar_builder.pipeline.io import write_bytes

# ACDC label codes.
ACDC_BACKGROUND, ACDC_RV, ACDC_MYO, ACDC_LV = 0, 1, 2, 3

# Biventricular (beating) parameters: name -> (low, high), drawn uniformly. Normal adults.
BIVENTRICULAR_RANGES: dict[str, tuple[float, float]] = {
    # LV end-diastolic volume; CMR normal adults 120-160 ml (margin kept for voxelisation).
    "lv_edv_ml": (125.0, 155.0),
    # LV ejection fraction; normal 55-70 %.
    "lv_ef": (0.57, 0.68),
    # Base to endocardial apex at end-diastole.
    "lv_cavity_length_mm": (75.0, 95.0),
    # End-diastolic wall; CMR normal 7-11 mm.
    "lv_wall_mm": (7.0, 11.0),
    # Apical wall relative to the lateral wall.
    "lv_apex_wall_ratio": (0.6, 0.9),
    # Descent of the atrioventricular plane toward the (still) apex at end-systole: 12-15 mm in
    # normal adults (mitral annular plane systolic excursion); the LV shortens by as much.
    "av_descent_mm": (12.5, 14.5),
    # Net LV twist at end-systole, apex relative to base (normal 10-20 deg by tagged CMR; a little less here).
    "lv_twist_deg": (8.0, 14.0),
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
    # RV end-diastolic volume over the LV's: the RV is slightly larger (RV EDV 130-190 ml; its
    # ejection fraction follows from the stroke volumes, 46-70 % here).
    "rv_edv_ratio": (1.05, 1.2),
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



def sample_biventricular_params(rng: np.random.Generator) -> dict[str, float]:
    """Parameters of one beating biventricular subject, drawn from `BIVENTRICULAR_RANGES`."""
    return sample_uniform(BIVENTRICULAR_RANGES, rng)



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
# Share of the twist taken by the base (turning the other way): the apex turns ~2x the base.
_BASE_TWIST_SHARE = 1.0 / 3.0


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
    (R, L + apex wall) holding the myocardial volume constant. The LV shortens by the descent
    of the base plane toward the apex, in proportion to the ejected volume; the apex stays
    still in the world. The stack follows the base plane, so the base stays on a slice boundary
    (voxel counts measure volumes without whole-slice jumps) and each frame's affine moves the
    stack by the descent. The RV is an ellipsoid anchored inside the LV, beyond its axis (so the
    LV leaves a crescent of it), scaled per frame (bisection on its voxel count) to its target
    volume; its base descends with the LV's. Both twist about the long axis, linearly from
    base to apex, in proportion to the ejected volume.

    Parameters
    ----------
    params : dict from `sample_biventricular_params`.
    n_frames : frames T over the cycle (frame 1 at end-diastole).
    voxel_mm : voxel size (3,); the third axis is the slice axis (short-axis stack).

    Returns
    -------
    frames : list of T label maps (X, Y, Z) uint8, ACDC codes (0 bg, 1 RV, 2 myo, 3 LV).
    affines : (T, 4, 4) float64, voxel index -> RAS mm per frame; the slice normal is the LV
        long axis (toward the apex); frames differ only by a shift along it.
    info : dict with ed_frame, es_frame (1-based, ES at the smallest measured LV volume),
        lv_volume_ml, rv_volume_ml, myo_volume_ml (T,) lists measured from voxel counts,
        ef and rv_ef (measured), base_descent_mm and twist_deg (T,) lists as modelled,
        height_cm, weight_kg.
    """
    p = params
    spacing = np.asarray(voxel_mm, float)
    voxel_ml = float(np.prod(spacing)) / 1000.0
    volume = _lv_volume_curve(np.arange(n_frames) / n_frames, p)

    # LV geometry per frame: cavity (r, L) from its volume and long-axis shortening; epicardium
    # from the constant myocardial volume. Shortening and twist follow the ejected fraction.
    ejected = (1.0 - volume) / p["lv_ef"]  # 0 at end-diastole, 1 at end-systole
    descent = p["av_descent_mm"] * ejected
    twist = np.radians(p["lv_twist_deg"]) * ejected
    cavity_ml = p["lv_edv_ml"] * volume
    cavity_length = p["lv_cavity_length_mm"] - descent
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

    def rv_mask(kappa: float, length: float, xr, yr, epicardium: np.ndarray) -> np.ndarray:
        depth, width = kappa * rv_axes[0], kappa * rv_axes[1]
        inside = (((xr - anchor - depth) / depth) ** 2 + (yr / width) ** 2 + (z / length) ** 2 <= 1.0) & (z >= 0.0)
        return inside & ~epicardium

    rv_edv_ml = p["rv_edv_ratio"] * p["lv_edv_ml"]
    rv_sv_ml = p["rv_sv_ratio"] * p["lv_edv_ml"] * p["lv_ef"]
    rv_target_ml = rv_edv_ml - rv_sv_ml * ejected

    frames = []
    for i in range(n_frames):
        # Twist: each slice turned about the long axis by an angle linear in its depth, the base
        # one way and the apex (share 1 - _BASE_TWIST_SHARE) the other.
        angle = twist[i] * (z / epi_length[i] - _BASE_TWIST_SHARE)
        xr, yr = x * np.cos(angle) + y * np.sin(angle), y * np.cos(angle) - x * np.sin(angle)
        cavity = _half_spheroid(xr, yr, z, cavity_radius[i], cavity_length[i])
        epicardium = _half_spheroid(xr, yr, z, epi_radius[i], epi_length[i])
        rv_length = rv_axes[2] * cavity_length[i] / cavity_length[0]
        # Smallest kappa whose RV holds the target: bisection on the (monotone) voxel count.
        low, high = 0.2, 3.0
        for _ in range(30):
            mid = 0.5 * (low + high)
            if np.count_nonzero(rv_mask(mid, rv_length, xr, yr, epicardium)) * voxel_ml < rv_target_ml[i]:
                low = mid
            else:
                high = mid
        labels = np.zeros((n_xy[0], n_xy[1], n_z), np.uint8)
        labels[rv_mask(high, rv_length, xr, yr, epicardium)] = ACDC_RV
        labels[epicardium] = ACDC_MYO
        labels[cavity] = ACDC_LV
        frames.append(labels)

    axes = heart_axes(p["axis_azimuth_deg"], p["axis_elevation_deg"], p["axis_roll_deg"])
    # The stack's origin moves with the base plane, toward the apex, by the descent: in the
    # world the apex (base + epicardial length) stays where it was at end-diastole.
    shift = epi_length[0] - epi_length
    affines = np.tile(np.eye(4), (n_frames, 1, 1))
    affines[:, :3, :3] = axes.T * spacing
    affines[:, :3, 3] = axes.T @ first + shift[:, None] * axes[2]

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
        "base_descent_mm": shift.tolist(),
        "twist_deg": np.degrees(twist).tolist(),
        "height_cm": round(p["height_cm"], 1),
        "weight_kg": round(p["weight_kg"], 1),
    }
    return frames, affines, info


def write_acdc_subject(folder: Path, patient_id: str, rng: np.random.Generator, n_frames: int = 20,
                       voxel_mm=(1.5, 1.5, 8.0)) -> Path:
    """Draw one beating heart and write it in the ACDC layout: `<folder>/<patient_id>/Info.cfg`
    and `<patient_id>_frameYY_gt.nii.gz` for every frame YY = 01..T (e.g. patient_id
    "patient001"). Returns the patient folder. Byte-identical for the same generator state."""
    frames, affines, info = biventricular_frames(sample_biventricular_params(rng), n_frames, voxel_mm)
    subject = Path(folder) / patient_id
    for index, (labels, affine) in enumerate(zip(frames, affines), start=1):
        write_bytes(subject / f"{patient_id}_frame{index:02d}_gt.nii.gz", nifti_gz_bytes(labels, affine))
    # Group NOR: the sampled ranges are those of normal subjects.
    cfg = (f"ED: {info['ed_frame']}\nES: {info['es_frame']}\nGroup: NOR\nHeight: {info['height_cm']:.1f}\n"
           f"NbFrame: {n_frames}\nWeight: {info['weight_kg']:.1f}\n")
    write_bytes(subject / "Info.cfg", cfg.encode("ascii"))
    return subject
