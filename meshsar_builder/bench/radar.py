"""Radar benchmark: seconds per view on one core for both facet models and the diffuse part, production echo vs
direct, Embree rays, the speckle statistics (bench.speckle, radar.appearance); on a GPU (`--device cuda`), the
GPU radar's seconds per view against one core instead (bench.radar_gpu, in run()'s child process).

run() measures in a child process started with OMP/OPENBLAS/MKL/NUMBA thread counts
of 1 (they are read once, when numpy and numba load) and pinned to one CPU with
sched_setaffinity, so BLAS, FFT, Embree and the echo kernel all run on one core.
Every timing is the minimum of a few repeats: the machines this runs on are shared.
The echo's first call in a process also pays for its numba kernels: compiling them
(timed once more in a child with an empty NUMBA_CACHE_DIR) or loading them from the
cache that numba keeps in __pycache__.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from meshsar_builder.bench import result_name
from meshsar_builder.pipeline.io import read_json, write_json

TARGET_SPEEDUP = 100.0
TARGET_ERROR = 1e-4
TARGET_VIEW_SECONDS = 0.5  # a whole view, the diffuse part included (issue 32 item 2)
TARGET_PO_OVER_CENTROID = 2.5  # whole view, the facet integral against the centroid model
TARGET_DIFFUSE_SECONDS = 0.15  # the diffuse part's echo per view (issue 29 item 5)
DIRECT_ANTENNAS = 48  # the direct sum is timed on this many antennas and scaled to the aperture
REPEATS = 3
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                    "NUMBA_NUM_THREADS")


def _best(function, repeats=REPEATS):
    """(minimum seconds, last result) over repeats."""
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - start)
    return best, result


def first_echo_seconds() -> float:
    """Seconds of the first echo call in this process (a small one): kernel compile or cache load.

    One facet on a 32 x 32 aperture: its cluster is interpolated, so the factorised echo's
    kernels load along with the series'.
    """
    import meshsar_builder.radar.echo as RE
    import meshsar_builder.radar.params as RP

    radar = RP.RadarParams(aperture=(32, 32), n_samples=8, echo_decimation=(1, 1, 1), loss_decimation=(1, 1, 1))
    tri = np.array([[[0.0, 0.0, 0.0], [5.0, 0.0, 1.0], [0.0, 0.0, 5.0]]])
    start = time.perf_counter()
    RE.echo(tri, np.ones(1), RP.aperture(radar, "anterior"), RP.frequencies(radar), radar)
    return time.perf_counter() - start


def view_seconds(verts, faces, intersector, radar, images, view, scatterers=None) -> dict:
    """Best-of-REPEATS seconds of one view as render_sample does it: visibility, echo, diffuse echo, imaging (signal and noise).

    scatterers : radar.diffuse.Scatterers on this mesh, or None for no diffuse part, whose
    seconds are those it adds to the echo call (its power on the stored echo grid included).
    `signal` is the specular echo alone (what the accuracy and GPU rows compare).
    """
    import meshsar_builder.radar.diffuse as RD
    import meshsar_builder.radar.echo as RE
    import meshsar_builder.radar.params as RP
    import meshsar_builder.radar.visibility as RV
    from meshsar_builder.radar.imaging import view_volume

    freqs, (x_mm, y_mm) = RP.frequencies(radar), RP.aperture_axes(radar)
    t_vis, (vis, _) = _best(lambda: RV.visibility(verts, faces, RP.probe_points(radar, view), intersector))
    seen = vis > 0
    positions = RP.aperture(radar, view)  # as render_sample passes it: the grid, which the echo factorises on
    t_echo, signal = _best(lambda: RE.echo(verts[faces][seen], vis[seen], positions, freqs, radar))
    t_diffuse, lit_count = 0.0, 0
    if scatterers is not None:  # as render_sample adds it: in the same call, sharing the clusters, and alone
        lit = RD.seen_by(*RD.place(verts, faces, scatterers, radar), scatterers.face, vis)  # on the echo grid
        lit_count = len(lit[2])
        t_both, _ = _best(lambda: RE.echo(verts[faces][seen], vis[seen], positions, freqs, radar,
                                          diffuse=(*lit, RD.lambert(radar)),
                                          diffuse_on=RP.grid_indices(radar, radar.echo_decimation)))
        t_diffuse = max(t_both - t_echo, 0.0)
    signal = signal.reshape(*radar.aperture, radar.n_samples)
    t_img, volume = _best(lambda: view_volume(signal, freqs, x_mm, y_mm, radar.z0_mm, images))
    return {"visible_facets": int(seen.sum()), "visible_scatterers": lit_count, "seconds_visibility": t_vis,
            "seconds_echo": t_echo, "seconds_diffuse": t_diffuse,
            "seconds_imaging": 2 * t_img,  # the signal's image and the noise's own
            "seconds_view": t_vis + t_echo + t_diffuse + 2 * t_img, "signal": signal, "volume": volume, "seen": seen,
            "vis": vis}


def relative(got: np.ndarray, expected: np.ndarray) -> float:
    """Relative L2 error of got against expected."""
    return float(np.linalg.norm(got - expected) / np.linalg.norm(expected))


def direct_check(verts, faces, radar, view, cpu: dict) -> dict:
    """The same model's direct sum on DIRECT_ANTENNAS antennas of a view, against the production echo there.

    cpu : view_seconds' dict of that view. Returns the direct sum's one-core seconds scaled
    to the whole aperture, the production echo's relative error on those antennas, and the
    antennas' indices with the direct echo (DIRECT_ANTENNAS, N) (for the GPU row).
    """
    import meshsar_builder.radar.echo as RE
    import meshsar_builder.radar.params as RP

    positions, freqs = RP.aperture_positions(radar, view), RP.frequencies(radar)
    subset = np.linspace(0, len(positions) - 1, DIRECT_ANTENNAS).round().astype(int)
    seen, vis = cpu["seen"], cpu["vis"]
    t_direct, direct = _best(lambda: RE.echo(verts[faces][seen], vis[seen], positions[subset], freqs, radar,
                                             method="direct"))
    production = cpu["signal"].reshape(len(positions), -1)[subset]
    return {"seconds_echo_direct_scaled": t_direct * len(positions) / len(subset),
            "echo_relative_error": relative(production, direct),
            "direct_antennas": subset, "direct": direct}


# Floating-point operations per antenna-scatterer pair of the production kernel
# (radar.series._chebyshev_echo), counted from its source with a multiply-add as 2 and a
# square root, division, min or max as 1 (they take more cycles; the measured rate absorbs
# that). L is the number of Chebyshev terms (the mean over antennas, each with its own length).
# Facet integral: the distance, cos theta and two corner projections (32), the lobe at an
# integer p (6), the amplitude, delay, the three corner weights and the cancellation test
# (37), per corner its phase and cos / sin polynomials, weights and Chebyshev argument (52);
# then per corner lane 6 flops for l = 0, 1 and 7 per further term (the recurrence and the
# complex accumulation).
FLOPS_PO = (32 + 6 + 37 + 3 * 52 + 3 * 6, 3 * 7)  # (per pair, per pair and term beyond l = 1)
# Point scatterer (centroid model, diffuse part): distance and cos (17), lobe (6), amplitude,
# delay, phase, cos / sin, weights and argument (57), then one lane.
FLOPS_POINT = (17 + 6 + 57 + 6, 7)
# Bytes a pair reads: the scatterer's row of the kernel's input, 13 float64 (facet) or 8
# (point), streamed once per antenna from the cache that holds K rows (6,000 facets: 624 KB).
BYTES_PO, BYTES_POINT = 13 * 8, 8 * 8
ROOFLINE_TOLERANCES = (1e-2, 1e-4, 1e-6, 1e-8, 1e-10)


def machine_rates() -> dict:
    """One core's practical peaks: float64 matrix multiply (GFLOP/s) and a streaming add (GB/s)."""
    a = np.random.default_rng(0).standard_normal((1536, 1536))
    t, _ = _best(lambda: a @ a)
    x, y = np.ones(1 << 25), np.ones(1 << 25)
    out = np.empty_like(x)
    t_add, _ = _best(lambda: np.add(x, y, out=out))
    return {"dgemm_gflops": 2 * 1536**3 / t / 1e9, "stream_add_gb_per_s": 3 * x.nbytes / t_add / 1e9}


def roofline(verts, faces, radar, view: str, scatterers) -> dict:
    """The echo's time per pair against its flop count, for the facet integral and the diffuse part.

    The series is cut at looser tolerances (fewer terms L) and the kernel timed at each: a line
    seconds = pairs x (setup + L x per_term) splits a pair's time into its set-up (distance,
    angles, phases) and its series; their flop counts (FLOPS_PO, FLOPS_POINT) over those
    times give the rates this core reaches. Exact near-normal pairs: the facet echo timed
    with none flagged (CORNER_GAIN_LIMIT infinite), against the default.
    """
    import meshsar_builder.radar.diffuse as RD
    import meshsar_builder.radar.echo as RE
    import meshsar_builder.radar.params as RP
    import meshsar_builder.radar.series as RS
    import meshsar_builder.radar.visibility as RV

    freqs, positions = RP.frequencies(radar), RP.aperture_positions(radar, view)
    vis, _ = RV.visibility(verts, faces, RP.probe_points(radar, view))
    seen = vis > 0
    tri = verts[faces][seen]
    lit = RD.seen_by(*RD.place(verts, faces, scatterers, radar), scatterers.face, vis)
    cases = {
        "po": (lambda: RE.echo(tri, vis[seen], positions, freqs, radar), int(seen.sum()), FLOPS_PO, BYTES_PO),
        "diffuse": (lambda: RE.point_echo(*lit, positions, freqs, RD.lambert(radar)), len(lit[2]), FLOPS_POINT,
                    BYTES_POINT),
    }
    default_tolerance, buckets = RS.CHEBYSHEV_TOLERANCE, RS._order_buckets
    used = []  # each call's series length, the mean over its antennas (each of which sums every item here)

    def recording(halves, omega_per_mm, tolerance):
        bucket, half = buckets(halves, omega_per_mm, tolerance)
        used.append(float(np.mean(RS._series_order(omega_per_mm * half, tolerance)[bucket])))
        return bucket, half

    out = {"view": view, "antennas": len(positions), "frequencies": len(freqs)}
    try:
        RS._order_buckets = recording
        for name, (run, count, (setup_flops, term_flops), pair_bytes) in cases.items():
            pairs = count * len(positions)
            rows = []
            for tolerance in ROOFLINE_TOLERANCES:
                RS.CHEBYSHEV_TOLERANCE = tolerance
                seconds, _ = _best(run)
                rows.append((used[-1], seconds))
            terms, seconds = np.array(rows, dtype=float).T
            per_term = np.polyfit(terms, seconds / pairs, 1)[0]  # seconds per pair and term
            full = float(terms[-1])
            flops = setup_flops + term_flops * (full - 2)
            series = per_term * (full - 2)  # seconds per pair in the terms beyond l = 1
            out[name] = {
                "pairs": pairs, "terms": full, "ns_per_pair": 1e9 * seconds[-1] / pairs,
                "flops_per_pair": flops, "gflops": flops * pairs / seconds[-1] / 1e9,
                "bytes_per_pair": pair_bytes, "flops_per_byte": flops / pair_bytes,
                "series_share": series * pairs / seconds[-1],
                "setup_gflops": setup_flops / (seconds[-1] / pairs - series) / 1e9,
                "series_gflops": term_flops / per_term / 1e9,
                "terms_and_seconds": [[float(a), float(b)] for a, b in rows],
            }
    finally:
        RS.CHEBYSHEV_TOLERANCE, RS._order_buckets = default_tolerance, buckets
    gain = RS.CORNER_GAIN_LIMIT
    try:
        RS.CORNER_GAIN_LIMIT = math.inf
        unflagged, _ = _best(cases["po"][0])
    finally:
        RS.CORNER_GAIN_LIMIT = gain
    with_exact, _ = _best(cases["po"][0])
    out["po"]["exact_pairs_share_of_time"] = max(0.0, (with_exact - unflagged) / with_exact)
    return out


def factorised_profile(verts, faces, radar, view: str) -> dict:
    """Where the factorised echo's time goes on a view: the series on the clusters' grids, and the rest
    (interpolation and phases, radar.factorised._spread_cluster), with the clusters' sizes."""
    import meshsar_builder.radar.echo as RE
    import meshsar_builder.radar.factorised as RF
    import meshsar_builder.radar.params as RP
    import meshsar_builder.radar.series as RS
    import meshsar_builder.radar.visibility as RV

    freqs, grid = RP.frequencies(radar), RP.aperture(radar, view)
    vis, _ = RV.visibility(verts, faces, RP.probe_points(radar, view))
    seen = vis > 0
    tri = verts[faces][seen]
    direct, clusters = RF.factorised_clusters(tri.mean(axis=1), tri, grid, float(RS._wavenumbers(freqs).max()))
    series, timed = RS._series_echo, {}

    def timing(*args, **kwargs):
        start = time.perf_counter()
        out = series(*args, **kwargs)
        timed["seconds"] = min(timed.get("seconds", math.inf), time.perf_counter() - start)
        timed["pairs"], timed["antennas"] = int((args[3] - args[2]).sum()), len(args[1])
        return out

    try:
        RS._series_echo = timing
        total, _ = _best(lambda: RE.echo(tri, vis[seen], grid, freqs, radar))
    finally:
        RS._series_echo = series
    grids = [len(x) * len(y) for _, _, _, x, y in clusters]
    return {"view": view, "clusters": len(clusters), "cell_mm": RF.FACTORISED_CELL_MM,
            "facets_on_the_aperture": int(len(direct)), "grid_antennas_median": float(np.median(grids)),
            "series_antennas": timed["antennas"], "series_pairs": timed["pairs"],
            "pairs_share_of_the_series": timed["pairs"] / (int(seen.sum()) * len(grid.positions)),
            "seconds": total, "seconds_series": timed["seconds"], "seconds_interpolation": total - timed["seconds"]}


SCALING_VERTICES = (1500, 3000, 6000, 12000)  # mesh sizes (the demo template has 6,000)
SCALING_APERTURES = (20, 40, 80)  # antennas a side over the same 160 mm (steps 8, 4, 2 mm)


def scaling(verts, faces, images, radar=None, vertex_counts=SCALING_VERTICES, sides=SCALING_APERTURES) -> dict:
    """How one view's echo and imaging grow with the mesh and the aperture: seconds and log-log exponents.

    verts, faces: a heart surface finer than the largest of vertex_counts, simplified to each
    (centred). The aperture keeps its extent (160 mm at the defaults) and z0 and takes
    `sides` antennas a side. Facet integral with the diffuse part, anterior view, best of
    REPEATS on this core; radar defaults to RadarParams().
    """
    import dataclasses

    import meshsar_builder.radar.diffuse as RD
    import meshsar_builder.radar.params as RP
    import meshsar_builder.radar.visibility as RV
    from meshsar_builder.geometry.remesh import simplify

    radar = radar or RP.RadarParams()
    extent = radar.aperture[0] * radar.step_mm
    meshes = []
    for count in vertex_counts:
        v, f = simplify(verts, faces, count)
        v = v - (v.min(axis=0) + v.max(axis=0)) / 2
        meshes.append((v, f, RD.draw_scatterers(v, f, radar.diffuse_density_per_mm2, np.random.default_rng(0))))
    by_mesh = []
    for v, f, scatterers in meshes:
        row = view_seconds(v, f, RV.embree_intersector(v, f), radar, images, "anterior", scatterers)
        by_mesh.append({"faces": int(len(f)), "visible_facets": row["visible_facets"],
                        **{k: row[k] for k in ("seconds_echo", "seconds_diffuse", "seconds_imaging")}})
    v, f, scatterers = meshes[len(meshes) // 2]
    by_aperture = []
    for side in sides:
        sized = dataclasses.replace(radar, aperture=(side, side), step_mm=extent / side)
        row = view_seconds(v, f, RV.embree_intersector(v, f), sized, images, "anterior", scatterers)
        by_aperture.append({"antennas": side * side,
                            **{k: row[k] for k in ("seconds_echo", "seconds_diffuse", "seconds_imaging")}})

    def exponent(rows, x):
        # None where a time is not positive: the diffuse part's is the difference of two timed calls
        # (view_seconds), which on a small scene can come out at zero and has no logarithm then
        keys = ("seconds_echo", "seconds_diffuse", "seconds_imaging")
        return {k: float(np.polyfit(np.log([r[x] for r in rows]), np.log([r[k] for r in rows]), 1)[0])
                if min(r[k] for r in rows) > 0 else None for k in keys}

    return {"by_mesh": by_mesh, "by_aperture": by_aperture,
            "exponent_faces": exponent(by_mesh, "visible_facets"), "exponent_antennas": exponent(by_aperture,
                                                                                                 "antennas")}


def speckle_row(verts, faces, radar, images, seeds: int = 5) -> dict:
    """The diffuse part's statistics: on a plate (bench.speckle.plate_statistics) and on this heart.

    On the heart, per view and seed (render_sample with the sample's own scatterers and
    noise), radar.appearance's figures; their medians over views and seeds.
    """
    from meshsar_builder.bench.speckle import plate_statistics
    from meshsar_builder.radar.render import render_sample

    looks = [view["appearance"] for seed in range(seeds)
             for view in render_sample(verts, faces, radar, images, np.random.default_rng(seed))["views"]]
    keys = ("speckle_share", "peak_over_median_db", "depth_error_median_mm", "depth_within_5mm")
    return {"plate": plate_statistics(seeds),
            "heart": {"seeds": seeds, "views": len(looks),
                      **{key: {"median": float(np.median([look[key] for look in looks])),
                               "min": float(np.min([look[key] for look in looks])),
                               "max": float(np.max([look[key] for look in looks]))} for key in keys}}}


def speckle_targets(speckle: dict) -> dict:
    """Issue 29's checks as targets with a `met` flag, under keys that name the speckle or the diffuse part."""
    plate, heart = speckle["plate"], speckle["heart"]

    def within(key, value, target, tolerance):
        return {key: {"target": f"{target} +- {tolerance}", "measured": value, "met": abs(value - target) <= tolerance}}

    def at_least(key, value, target):
        return {key: {"target": f">= {target}", "measured": value, "met": value >= target}}

    def at_most(key, value, target):
        return {key: {"target": f"<= {target}", "measured": value, "met": value <= target}}

    return {
        **within("speckle_plate_contrast", plate["contrast"], 1.0, 0.1),
        **at_least("speckle_plate_rayleigh_ks_pvalue", plate["ks_pvalue"], 0.01),
        **within("diffuse_doubled_area_power_db", plate["doubled_area_power_db"], 3.0, 0.5),
        **within("diffuse_doubled_area_mean_db", plate["doubled_area_mean_db"], 0.0, 0.5),
        **within("speckle_grain_over_psf", plate["grain_over_psf"], 1.0, 0.25),
        **at_least("speckle_share_median", heart["speckle_share"]["median"], 0.5),
        **at_least("speckle_peak_over_median_db_min", heart["peak_over_median_db"]["min"], 10.0),
        **at_most("speckle_depth_error_median_mm", heart["depth_error_median_mm"]["median"], 3.0),
        **at_least("speckle_depth_within_5mm", heart["depth_within_5mm"]["median"], 0.8),
    }


def measure(verts: np.ndarray, faces: np.ndarray, fine: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """The benchmark numbers at default parameters (call on one core; run() arranges that).

    fine: a finer surface of the same heart for the scaling row (left out without it).
    """
    import dataclasses

    import meshsar_builder.radar.diffuse as RD
    import meshsar_builder.radar.echo as RE
    import meshsar_builder.radar.params as RP
    import meshsar_builder.radar.visibility as RV
    from meshsar_builder.radar.imaging import ImageParams

    first_call = first_echo_seconds()
    radar, images = RP.RadarParams(), ImageParams()
    centroid = dataclasses.replace(radar, facet="centroid")
    freqs = RP.frequencies(radar)
    _, normals, _ = RV.facet_geometry(verts, faces)
    intersector = RV.embree_intersector(verts, faces)
    scatterers = RD.draw_scatterers(verts, faces, radar.diffuse_density_per_mm2, np.random.default_rng(0))
    views, ray_count, ray_seconds = [], 0, 0.0
    for view in radar.views:
        po = view_seconds(verts, faces, intersector, radar, images, view, scatterers)
        point = view_seconds(verts, faces, intersector, centroid, images, view)
        check = direct_check(verts, faces, radar, view, po)
        seen, vis = po.pop("seen"), po.pop("vis")
        po.pop("volume"), po.pop("signal")
        positions = RP.aperture_positions(radar, view)
        t_series, _ = _best(lambda: RE.echo(verts[faces][seen], vis[seen], positions, freqs, radar,
                                            method="chebyshev"))
        direct_scaled, error = check["seconds_echo_direct_scaled"], check["echo_relative_error"]
        # Embree alone: the same rays as the visibility pass, without the numpy around them.
        probes = RP.probe_points(radar, view)
        centres = RV.facet_geometry(verts, faces)[0]
        to_probe = probes[None] - centres[:, None]
        facet, probe = np.nonzero(np.einsum("fc,fpc->fp", normals, to_probe) > 0)
        directions = to_probe[facet, probe] / np.linalg.norm(to_probe[facet, probe], axis=1, keepdims=True)
        origins = centres[facet] + RP.RAY_OFFSET_MM * normals[facet]
        t_rays, _ = _best(lambda: intersector.intersects_any(origins, directions))
        ray_count, ray_seconds = ray_count + len(facet), ray_seconds + t_rays
        views.append({
            "view": view,
            "visible_facets": po["visible_facets"],
            "antenna_facet_pairs": po["visible_facets"] * len(positions),
            **{key: value for key, value in po.items() if key.startswith("seconds")},
            "centroid": {key: value for key, value in point.items() if key.startswith("seconds")},
            "po_over_centroid_echo": po["seconds_echo"] / point["seconds_echo"],
            # both without the diffuse part, which does not depend on the facet model
            "po_over_centroid_view": (po["seconds_view"] - po["seconds_diffuse"]) / point["seconds_view"],
            "diffuse_over_specular_echo": po["seconds_diffuse"] / po["seconds_echo"],
            "seconds_echo_direct_scaled": direct_scaled,
            "seconds_echo_series": t_series,  # the per-pair series (echo_method "chebyshev") on every antenna
            "factorised_speedup": t_series / po["seconds_echo"],
            "echo_speedup": direct_scaled / po["seconds_echo"],
            "echo_relative_error": error,
            "direct_antennas": DIRECT_ANTENNAS,
        })
    worst_view = max(v["seconds_view"] for v in views)
    worst_diffuse = max(v["seconds_diffuse"] for v in views)
    speckle = speckle_row(verts, faces, radar, images)
    speedup = min(v["echo_speedup"] for v in views)
    error = max(v["echo_relative_error"] for v in views)
    ratio = max(v["po_over_centroid_view"] for v in views)
    return {
        "mesh_faces": int(len(faces)),
        "echo_method": radar.echo_method,
        "facet": radar.facet,
        "threads": "one core: child process with " + ", ".join(f"{name}=1" for name in THREAD_VARIABLES)
                   + ", pinned with sched_setaffinity",
        "repeats": REPEATS,
        "echo_first_call_seconds": first_call,
        "views": views,
        "embree_rays_per_second": ray_count / ray_seconds,
        "machine": machine_rates(),
        "roofline": roofline(verts, faces, radar, radar.views[0], scatterers),
        "factorised": factorised_profile(verts, faces, radar, radar.views[0]),
        "scaling": scaling(*fine, images) if fine is not None else None,
        "speckle": speckle,
        "targets": {
            "diffuse_seconds_per_view": {"target": TARGET_DIFFUSE_SECONDS, "measured_max": worst_diffuse,
                                         "met": worst_diffuse <= TARGET_DIFFUSE_SECONDS},
            **speckle_targets(speckle),
            "echo_speedup": {"target": TARGET_SPEEDUP, "measured_min": speedup, "met": speedup >= TARGET_SPEEDUP},
            "echo_relative_error": {"target": TARGET_ERROR, "measured_max": error, "met": error <= TARGET_ERROR},
            "seconds_per_view": {"target": TARGET_VIEW_SECONDS, "measured_max": worst_view,
                                 "met": worst_view <= TARGET_VIEW_SECONDS},
            "po_over_centroid_view": {"target": TARGET_PO_OVER_CENTROID, "measured_max": ratio,
                                      "met": ratio <= TARGET_PO_OVER_CENTROID},
        },
    }


def run(out_dir: Path, verts: np.ndarray, faces: np.ndarray, fine: tuple[np.ndarray, np.ndarray] | None = None,
        device: str = "cpu") -> dict:
    """Benchmark the radar on a mesh (verts (n, 3) mm heart frame, faces (m, 3)); writes out_dir/'radar.json', or
    on a GPU (device "cuda" or "cuda:N") the GPU row alone to 'radar-cuda.json' (bench.radar_gpu).

    fine: (verts, faces) of a finer surface of the same heart, for the scaling row.
    """
    if device != "cpu":
        from meshsar_builder.radar.gpu import check_device

        check_device(device)  # a missing torch or GPU is named before the CPU half's minutes
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    mesh_path, result_path = out_dir / "radar-bench-mesh.npz", out_dir / result_name("radar", device)
    extra = {} if fine is None else {"fine_verts": np.asarray(fine[0], dtype=np.float64),
                                     "fine_faces": np.asarray(fine[1], dtype=np.int64)}
    np.savez(mesh_path, verts=np.asarray(verts, dtype=np.float64), faces=np.asarray(faces, dtype=np.int64), **extra)
    env = {**os.environ, **{name: "1" for name in THREAD_VARIABLES}}
    module = __name__ if device == "cpu" else "meshsar_builder.bench.radar_gpu"
    try:
        subprocess.run([sys.executable, "-m", module, str(mesh_path), str(result_path), device], env=env, check=True)
    finally:
        mesh_path.unlink(missing_ok=True)
    result = read_json(result_path)
    if device != "cpu":
        return result
    with tempfile.TemporaryDirectory() as cache:
        compile_run = subprocess.run([sys.executable, "-m", __name__, "--first-echo"], check=True, text=True,
                                     env={**env, "NUMBA_CACHE_DIR": cache}, capture_output=True)
    result["echo_compile_seconds"] = float(compile_run.stdout.split()[-1])
    write_json(result_path, result)
    return result


def pin_one_core() -> None:
    """Run this process on one CPU (the benchmark's child; its thread counts are set by run())."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def _main(mesh_path: str, result_path: str | None = None, device: str = "cpu") -> None:
    pin_one_core()
    if mesh_path == "--first-echo":
        print(first_echo_seconds())
        return
    with np.load(mesh_path) as mesh:
        fine = (mesh["fine_verts"], mesh["fine_faces"]) if "fine_verts" in mesh else None
        write_json(result_path, measure(mesh["verts"], mesh["faces"], fine))


if __name__ == "__main__":
    _main(*sys.argv[1:])
