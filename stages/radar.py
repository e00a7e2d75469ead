"""Stage `radar`: SAR images and decimated echo of every dataset mesh (DESIGN sections 4, 5).

Dataset meshes are the shape model's samples (sources with `use = "ssm"`), the
samples of external shape models (`kind = "shape_model"` sources) and the
remeshed meshes of sources with `use = "direct"` (every frame; the frames of a beating
subject as its reference mesh fitted to each, stages/track.py, meta `correspondence`). Each is
moved to its heart-centred frame (minus the centre of its bounding box; for the frames
of one subject, the centre of its ED or first frame's box, shared by all) and scanned
from every view of `[radar]`.

Outputs: `radar/<sample>.npz` with `sar` (V, C, H, W) float16, `echo`
(V, Ex, Ey, Ef) complex64, `echo_clean` (V, Lx, Ly, Lf) complex64 (the noise-free echo on
the loss grid), `noise_seed` (V,) uint64, `noise_sigma` (V,) float64 and `center_mm`
(3,) float32; the sidecar holds the
sample's metadata and per-view figures (visible facets and scatterers, powers, raw SNR,
image noise floor, seconds). With the diffuse part on (`[radar] diffuse`), meta
`scatterers` names the mesh its scatterers were drawn on and seeded by
(scatterer_mesh).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from meshsar_builder.dataset.frames import direct_meshes, source_cohorts, subject_series
from meshsar_builder.geometry.meshfile import read_ply
from meshsar_builder.pipeline.errors import MeshsarError
from meshsar_builder.pipeline.io import atomic_path
from meshsar_builder.pipeline.runner import Context, Item, Results, Stage
from meshsar_builder.pipeline.seeding import item_rng
from meshsar_builder.radar.diffuse import draw_scatterers
from meshsar_builder.radar.render import compile_kernels, render_sample

NAME = "radar"


def dataset_meshes(ctx: Context, results: Results) -> list[tuple[str, str, dict]]:
    """(sample id, mesh path, metadata) of every dataset mesh, in a fixed order."""
    out = []
    # The sample parts' samples (not the model's or a specificity part's records), in sample order.
    drawn = sorted((sid, s, rec["sources"]) for rec in results.of("ssm").values()
                   for sid, s in rec.get("samples", {}).items())
    for sid, s, sources in drawn:
        meta = {"source": "+".join(sources), "subject": sid, "frame": None, "phase": "",
                "provenance": "ssm", "subset": "ssm", "ssm_coeffs": s["coeffs"]}
        out.append((sid, str(ctx.stage_dir("ssm") / "samples" / f"{sid}.ply"), meta))
    for name, rec in results.of("sources").items():
        for sid, s in rec.get("shape_samples", {}).items():  # an external shape model's samples
            meta = {"source": name, "subject": sid, "frame": None, "phase": "", "provenance": "shape_model",
                    "subset": "ssm", "ssm_coeffs": s["coeffs"], "shape_model": rec["shape_model"]}
            out.append((sid, str(ctx.stage_dir("sources") / name / f"{sid}.ply"), meta))
    cohorts = source_cohorts(ctx.recipe.sources)
    direct = direct_meshes(results.of("remesh"), cohorts)
    reference = {mid: ref for mids, ref in subject_series(direct, cohorts) for mid in mids}
    tracked = {mid: (rec, report) for rec in results.of("track").values() for mid, report in rec["frames"].items()}
    for mid, rec in direct.items():
        meta = {k: rec[k] for k in ("source", "subject", "frame", "phase", "cycle_fraction", "provenance")}
        if rec["source"] in cohorts:  # sources sharing subject names: splits group across them
            meta["cohort"] = cohorts[rec["source"]]
        if rec.get("replaces"):  # the cohort's other maps of this frame, left out (direct_meshes)
            meta["replaces"] = rec["replaces"]
        if rec["frame"] is not None or rec["phase"]:  # a frame: the heart frame of its subject's reference
            meta["reference_frame"] = reference[mid]
        path = ctx.stage_dir("remesh") / f"{mid}.ply"
        if mid in tracked:  # a beating subject's frame: the reference mesh fitted to it (stages/track.py)
            track, report = tracked[mid]
            path = ctx.stage_dir("track") / f"{mid}.ply"
            meta["correspondence"] = ("reference" if mid == track["reference"] else "tracked" if report["tracked"]
                                      else f"own mesh (fit rejected: {report['rejected']})")
        out.append((mid, str(path), {**meta, "subset": "direct"}))
    return out


# The GPU path's version: 2 sums the factorised echo's grids on the GPU (1 summed every antenna directly, which
# follows a CPU build to the factorisation's 1-5e-5 only).
GPU_VERSION = 2


def item_params(ctx: Context) -> dict:
    """What a sample's outputs depend on besides its mesh: the radar and image parameters and the seed.

    `device` is left out for "cpu", so the parameter hash of a CPU build is the one it had
    before the key existed (built samples stay up to date); a CUDA build adds "device":
    "cuda" (its bits differ by rounding), whatever the device index, which changes no bits,
    and the GPU path's own version (GPU_VERSION), so its samples alone are rebuilt when it changes.
    """
    radar = dataclasses.asdict(ctx.recipe.radar)
    device = radar.pop("device")
    params = {"radar": radar, "images": dataclasses.asdict(ctx.recipe.images), "seed": ctx.recipe.seed}
    if device != "cpu":
        params["device"] = device.split(":")[0]
        params["device_version"] = GPU_VERSION
    return params


def resources(ctx: Context) -> dict | None:
    """On Dask, a CUDA radar's items go only to workers started with `--resources GPU=1`."""
    return {"GPU": 1} if ctx.recipe.radar.device != "cpu" else None


def check(ctx: Context) -> None:
    """Fail before the build starts when [radar] device (or --device) names a GPU this machine cannot use."""
    if ctx.recipe.radar.device != "cpu":
        from meshsar_builder.radar.gpu import check_device  # torch: only for a GPU radar

        check_device(ctx.recipe.radar.device)


def scatterer_mesh(ctx: Context, sid: str, path: str, meta: dict) -> tuple[str, str]:
    """(id, path) of the mesh a sample's diffuse scatterers are drawn on, and seeded by.

    A beating subject's frames in correspondence share its reference frame's scatterers,
    which then move with the tissue; any other mesh (a shape-model sample, a single
    frame, a frame whose fit was rejected) draws its own.
    """
    if meta.get("correspondence") in ("reference", "tracked"):
        ref = meta["reference_frame"]
        return ref, str(ctx.stage_dir("track") / f"{ref}.ply")
    return sid, path


def plan(ctx: Context, results: Results) -> list[Item]:
    params = item_params(ctx)
    remeshed = results.of("remesh")
    items = []
    for sid, path, meta in dataset_meshes(ctx, results):
        own = params
        if "reference_frame" in meta:  # the subject's shared centre: a change of it redoes the frame
            own = {**params, "center_mm": remeshed[meta["reference_frame"]]["center_mm"]}
        inputs = (path,)
        if ctx.recipe.radar.diffuse:
            ref, ref_path = scatterer_mesh(ctx, sid, path, meta)
            meta = {**meta, "scatterers": ref}
            inputs += (ref_path,) if ref_path != path else ()
        items.append(Item(sid, (f"{sid}.npz",), inputs=inputs, params=own, data=meta))
    return items


def run(ctx: Context, item: Item) -> dict:
    verts, faces, _ = read_ply(item.inputs[0])
    # A frame sits in its subject's reference frame (bounding-box centre of ED or the first
    # frame); any other mesh in its own.
    center = np.asarray(item.params["center_mm"]) if "center_mm" in item.params else (verts.min(axis=0) + verts.max(axis=0)) / 2
    rng = item_rng(ctx.recipe.seed, NAME, item.id)
    scatterers = None
    if ctx.recipe.radar.diffuse:
        ref_verts, ref_faces, _ = read_ply(item.inputs[-1])
        if not np.array_equal(ref_faces, faces):
            raise MeshsarError(f"{item.inputs[0]}: its faces differ from those of {item.inputs[-1]}, the mesh its "
                               f"diffuse scatterers are drawn on")
        scatterers = draw_scatterers(ref_verts, ref_faces, ctx.recipe.radar.diffuse_density_per_mm2,
                                     item_rng(ctx.recipe.seed, "diffuse", item.data["scatterers"]))
    out = render_sample(verts - center, faces, ctx.recipe.radar, ctx.recipe.images, rng, scatterers)
    with atomic_path(ctx.stage_dir(NAME) / f"{item.id}.npz") as tmp:
        np.savez(tmp, sar=out["sar"], echo=out["echo"], echo_clean=out["echo_clean"], noise_seed=out["noise_seed"],
                 noise_sigma=out["noise_sigma"], center_mm=center.astype(np.float32))
    # The image noise floor per view travels with the sample (shards' meta, the card).
    meta = {**item.data, "noise_floor_db": [v["noise_floor_db"] for v in out["views"]],
            # what each view's images look like against the mesh (speckle share, glints, depth), for the card
            "appearance": [{k: round(x, 4) if isinstance(x, float) else x for k, x in v["appearance"].items()}
                           for v in out["views"]]}
    # `mesh`: the sample's own mesh among the inputs (the shards stage reads it; a frame's
    # reference mesh may be an input too, for its scatterers).
    return {"meta": meta, "mesh": item.inputs[0], "center_mm": center.tolist(), "views": out["views"],
            "device": ctx.recipe.radar.device}


def warm(ctx: Context) -> None:
    compile_kernels(ctx.recipe.radar, ctx.recipe.images)


# Version 2: the physical-optics facet echo and the image-domain noise floor (image_snr_db).
# Version 3: echo_clean on the loss grid, and noise drawn from a stored uint64 seed per view.
# Version 4: frames of a subject share its ED (or first) frame's centre.
# Version 5: a beating subject's frames are its reference mesh fitted to each (stages/track.py).
# Version 6: the diffuse (speckle) part, scatterers shared by the frames in correspondence.
# Version 7: the series' sums in a new order (32 lanes, BLAS products) and the scatterers' series cut at 1e-7 on
# the factorised grids: echoes differ in their last bits, diffuse_power by the series' 1e-10.
# Version 8: the factorised echo interpolates in single precision (measured 1.6e-7 relative, far below the
# factorisation's 1e-5), and the scatterers' series on its grids is cut at 1e-5: echoes differ in their last bits.
# Version 9: diffuse_power from the diffuse part's own sums on the factorised clusters, interpolated onto the stored
# echo grid (1e-5 of its series sum on the demo heart; the echo's bytes unchanged), and no `diffuse` seconds of its own.
# Version 10: each antenna's series as long as its own range span needs (radar.series._order_buckets), not the
# longest over the aperture: echoes differ within the series' tolerance (4.5e-7 relative, a demo sample's stored
# echo).
# Version 11: the point scatterers' range bounds from squared distances again (one square root an antenna): echoes
# may differ in their last bits.
# Version 12: the factorised echo interpolates each cluster's frequency-series coefficients (echoes within 3e-6 of
# v11's on the demo heart), and the images' padded grid is 165 x 165 (was 162), so that inverse FFTs land on the
# pixels: the complex volumes grow by (165 / 162)^2 (their sums have more terms; every channel is a ratio) and the
# demo heart's intensity channels move by at most 0.003, its depth channels on 0.04 % of the pixels.
# Version 13: the factorised echo checks each cluster's interpolation of the facets and refines its grid where it
# has not converged (silhouettes of bumpy shapes were up to 1.2e-4 off the direct sum), and its first grids come
# from the Bessel bound at 1e-3 (15 % fewer antennas on the demo heart): echoes move within the factorisation's
# error (the demo heart's 1.1-2.6e-5 from the direct sum before, 1.5-2.8e-5 now).
# Version 14: the depth's detection test takes the noise image's RMS per range slice, at each pixel's peak (pure
# noise passed 1.75e-4 of the pixels against the whole volume's RMS, 2.0e-6 now), from a float64 sum.
# Version 15: a mesh reaching beyond the images' field of view (render.check_field_of_view) is refused.
# Version 16: facets with edges beyond sqrt(lambda R) / 4 (7.4 mm at the defaults) are split before the echo
# (render.echo_facets): a registered demo mesh splits 24-27 of its 11,996 faces, its echo moving 0.25-0.32 %.
STAGE = Stage(name=NAME, version=16, plan=plan, run=run, resources=resources, check=check, warm=warm)
