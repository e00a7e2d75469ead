"""Stage `card`: the dataset card, `card/README.md` with pictures and tables.

A gallery of samples (each mesh rendered from the views beside its SAR
channels), the shape model's variance explained and a mode strip (mean ± 3σ),
chamber volumes over the cycle of the dynamic subjects, counts per source,
subset and split, and the time each stage took per item. One item per figure
(gallery, speckle, shape model, cycle, motion), side by side; each returns its
section's lines, and `finish` writes README.md from them and the index (the
card was one 5-7 s item, the longest serial part of a small build).
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict

import numpy as np

from meshsar_builder.dataset import card
from meshsar_builder.dataset.frames import merge_cycles
from meshsar_builder.dataset.shards import INDEX_NAME
from meshsar_builder.dataset.splits import RESERVED, split_path
from meshsar_builder.geometry.meshfile import read_ply
from meshsar_builder.geometry.ssm import load_model
from meshsar_builder.pipeline.io import read_json, write_bytes
from meshsar_builder.pipeline.runner import STAGE_ORDER, Context, Item, Results, Stage
from meshsar_builder.pipeline.seeding import item_rng
from meshsar_builder.radar.render import render_sample

NAME = "card"
GALLERY = 6  # samples in the card's gallery; `meshsar preview --n N` draws more


def plan(ctx: Context, results: Results) -> list[Item]:
    index_path = ctx.out / INDEX_NAME
    if not index_path.exists() or not results.of("shards"):
        return []
    model = ctx.stage_dir("ssm") / "model.npz"
    tracks = merge_cycles(results.of("track").values())
    track = tracks[0] if tracks else None  # the first beating subject's frames in correspondence
    dynamic = [r for r in results.of("meshes").values() if r.get("frame") is not None]
    # Each figure from the index (it names every shard by its digest, so it changes with any sample) and what
    # else it reads.
    figures = [("gallery", ("gallery.png",), (), {})]
    if ctx.recipe.radar.diffuse:
        figures.append(("speckle", ("speckle.png",), (), {"track": track}))
    if model.exists():
        figures.append(("shape-model", ("ssm_variance.png", "ssm_modes.png"),
                        (model, ctx.stage_dir("ssm") / "report.json"), {}))
    if dynamic:
        figures.append(("cycle", ("cycle.png",), (), {"dynamic": dynamic}))
    if track is not None:
        frames = tuple(ctx.stage_dir("track") / f"{mid}.ply" for mid in track["frames"])
        counts = [[rec["reference"], len(rec["frames"]), len(rec["in_correspondence"])] for rec in tracks]
        figures.append(("motion", ("motion.png",), frames, {"track": track, "tracks": counts}))
    return [Item(name, outputs, inputs=tuple(str(p) for p in (index_path, *inputs)),
                 params={"gallery": GALLERY, "version": 1}, data=data) for name, outputs, inputs, data in figures]


def _median_range(values: list, digits: int) -> str:
    """'median (min – max)' of the finite values, '-' if there are none."""
    values = np.array([v for v in values if v is not None], dtype=float)
    values = values[np.isfinite(values)]
    if not len(values):
        return "-"
    return f"{np.median(values):.{digits}f} ({values.min():.{digits}f} – {values.max():.{digits}f})"


def radar_section(index: dict) -> list[str]:
    """The card's radar lines: echo model, noise, and per view the noise floor and appearance over the samples."""
    radar = index["radar"]
    noise = (f"image noise floor {radar['image_snr_db']} dB below the peak (`image_snr_db`)"
             if radar.get("image_snr_db") is not None else
             f"{radar['snr_db']} dB per raw sample (`snr_db`)" if radar.get("snr_db") is not None else "none")
    diffuse = (f"diffuse part on: sigma0 {radar['diffuse_sigma0_db']} dB (Lambert), "
               f"{radar['diffuse_density_per_mm2']} scatterers per mm²" if radar.get("diffuse") else "no diffuse part")
    samples = list(index["samples"].values())
    rows = []
    for v, view in enumerate(index["views"]):
        floors = [(s.get("noise_floor_db") or [None] * (v + 1))[v] for s in samples]
        looks = [s["appearance"][v] for s in samples if s.get("appearance")]
        rows.append([view["name"], _median_range(floors, 1),
                     *(_median_range([look.get(key) for look in looks], digits)
                       for key, digits in (("speckle_share", 2), ("peak_over_median_db", 1),
                                           ("depth_error_median_mm", 1), ("depth_within_5mm", 2)))])
    lines = ["## Radar", "", f"Echo model: facet `{radar.get('facet')}`, reflectivity `{radar.get('reflectivity')}`, "
             f"{diffuse}; noise: {noise}. The image noise floor is the RMS of the noise's own image, in dB below the "
             "noise-free image's peak; the intensity channel shows 40 dB. Per view over the samples, median "
             "(range): the share of the heart's silhouette within 20 dB of the view's peak (speckle-dominated "
             "images fill it), the peak over the silhouette's median intensity (glints stay visible), and per "
             "detected pixel the distance along its ray from the depth read to the mesh (median, and the share "
             "within 5 mm).", ""]
    lines += [card.markdown_table(["view", "noise floor (dB)", "within 20 dB of the peak", "peak over median (dB)",
                                   "depth error (mm)", "depth within 5 mm"], rows), ""]
    return lines


def speckle_section(ctx: Context, index: dict, track: dict | None, folder) -> list[str]:
    """speckle.png: the first gallery sample with and without the diffuse part, and a subject's speckle over its cycle."""
    sid = card.gallery_ids(index, 1)[0]
    sample = card.load_samples(ctx.out, index, [sid])[0]
    channel = index["channels"].index("intensity")
    # the same sample re-rendered without the diffuse part: same mesh, radar and noise seeds
    specular = render_sample(sample.verts.astype(np.float64), sample.faces,
                             dataclasses.replace(ctx.recipe.radar, diffuse=False), ctx.recipe.images,
                             item_rng(ctx.recipe.seed, "radar", sid))["sar"][:, channel]
    cycle = []
    if track is not None:
        frames = [mid for mid in track["frames"] if mid in index["samples"]]
        picked = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, min(8, len(frames))).round().astype(int))]
        for mid, s in zip(picked, card.load_samples(ctx.out, index, picked)):
            cycle.append((mid.rsplit("-", 1)[-1], s.sar[0, channel].astype(np.float32)))
    card.speckle_figure(sid, sample.sar[:, channel].astype(np.float32), specular.astype(np.float32), index["views"],
                        cycle, folder / "speckle.png")
    return ["## Speckle", "",
            "The diffuse part: point scatterers attached to the surface (radar/diffuse.py), whose images are "
            "fully developed speckle. Top: one sample as built and with the diffuse part off (same noise). Bottom: "
            "a beating subject's frames in correspondence share their scatterers, so its speckle moves with the "
            "tissue (a frame whose fit was rejected draws its own; meta `scatterers`).", "",
            "![speckle](speckle.png)", ""]


def gallery_section(ctx: Context, index: dict, folder) -> list[str]:
    """gallery.png: GALLERY samples, each mesh rendered from the views beside its SAR channels."""
    card.gallery(card.load_samples(ctx.out, index, card.gallery_ids(index, GALLERY)), index, folder / "gallery.png")
    return ["## Samples", "", "Each row: per view the mesh (coloured by structure, same field of view as the images), "
            "then the SAR channels (intensity in dB over the dynamic range; depth along w, red toward the radar).", "",
            "![gallery](gallery.png)", ""]


def shape_model_section(ctx: Context, folder) -> list[str]:
    """ssm_variance.png and ssm_modes.png: the variance explained and the mean +- 3 sigma along the first modes."""
    index = read_json(ctx.out / INDEX_NAME)
    report = read_json(ctx.stage_dir("ssm") / "report.json")
    card.ssm_variance_plot(report, folder / "ssm_variance.png")
    card.ssm_mode_strip(load_model(ctx.stage_dir("ssm") / "model.npz"), index["views"][0], index["fov_mm"],
                        folder / "ssm_modes.png")
    return ["## Shape model", "",
            f"{report['subjects']} registered subjects, {report['n_vertices']} vertices, {report['modes']} modes "
            f"({report['compactness'][-1] * 100:.1f} % of the variance). Generalisation (leave-one-out, all modes): "
            f"{report['generalisation_mm'][-1]:.2f} mm; specificity: {report['specificity_mm']:.2f} ± "
            f"{report['specificity_std_mm']:.2f} mm; self-intersecting draws redrawn: {report['self_intersection_redraws']}.", "",
            "![variance](ssm_variance.png)", "", "Mean ± 3σ along the first modes:", "", "![modes](ssm_modes.png)", ""]


def cycle_section(dynamic: list[dict], folder) -> list[str]:
    card.cycle_plot(dynamic, folder / "cycle.png")
    return ["## Dynamic subjects", "", "Chamber volumes over the cycle, from the label maps' voxel counts.", "",
            "![cycle](cycle.png)", ""]


def motion_section(ctx: Context, track: dict, tracks: list, folder) -> list[str]:
    card.motion_plot({mid: read_ply(ctx.stage_dir("track") / f"{mid}.ply") for mid in track["frames"]}, track,
                     folder / "motion.png")
    return ["## Frames in correspondence", "",
            "Each beating subject's reference frame (ED, else the first) fitted to every frame, so all its "
            "frames share one mesh (stages/track.py); a frame whose fit was rejected keeps its own mesh.", "",
            "![motion](motion.png)", "",
            card.markdown_table(["reference frame", "frames", "in correspondence"], tracks), ""]


def run(ctx: Context, item: Item) -> dict:
    """One figure of the card: its file(s), and its section's lines for README.md (finish)."""
    folder = ctx.stage_dir(NAME)
    if item.id == "gallery":  # and which samples it shows
        index = read_json(ctx.out / INDEX_NAME)
        return {"lines": gallery_section(ctx, index, folder), "gallery": card.gallery_ids(index, GALLERY)}
    if item.id == "speckle":
        lines = speckle_section(ctx, read_json(ctx.out / INDEX_NAME), item.data["track"], folder)
    elif item.id == "shape-model":
        lines = shape_model_section(ctx, folder)
    elif item.id == "cycle":
        lines = cycle_section(item.data["dynamic"], folder)
    else:
        lines = motion_section(ctx, item.data["track"], item.data["tracks"], folder)
    return {"lines": lines}


SECTION_ORDER = ("gallery", "speckle", "shape-model", "cycle", "motion")  # the radar section follows the gallery


def finish(ctx: Context, results: Results) -> None:
    """card/README.md: the index's summary, each figure's section (run), the radar lines, counts and time per stage."""
    records = results.of(NAME)
    if not records:
        return
    index = read_json(ctx.out / INDEX_NAME)
    lines = [f"# Dataset card: {index['recipe']}", "",
             f"{index['n_samples']} samples in {len(index['shards'])} shards; views "
             f"{', '.join(v['name'] for v in index['views'])}; images {index['image_size'][0]}×{index['image_size'][1]} "
             f"over {index['fov_mm']} mm; channels {', '.join(index['channels'])}. "
             f"Recipe sha256 `{index['recipe_sha256'][:12]}`, code {index['code_version']}.", ""]
    for name in SECTION_ORDER:
        lines += records[name]["lines"] if name in records else []
        lines += radar_section(index) if name == "gallery" else []
    split_file = split_path(ctx.out, ctx.recipe.splits.seed)
    split = read_json(split_file) if split_file.exists() else {}
    names = [k for k in split if k not in RESERVED]
    where = {sid: name for name in names for sid in split[name]}
    rows = defaultdict(lambda: defaultdict(int))
    for sid, s in index["samples"].items():
        rows[(s["source"], s["subset"])][where.get(sid, "-")] += 1
    header = ["source", "subset", "samples", *(f"{n} (seed {split['seed']})" for n in names)]
    table = [[src, sub, sum(c.values()), *(c.get(n, 0) for n in names)] for (src, sub), c in sorted(rows.items())]
    lines += ["## Counts", "", card.markdown_table(header, table), ""]
    timing = []
    for stage in STAGE_ORDER:
        secs = [r["seconds"] for r in results.of(stage).values()]
        if secs:
            timing.append([stage, len(secs), round(sum(secs), 1), round(sum(secs) / len(secs), 2)])
    lines += ["## Time per stage", "", "Item seconds as recorded in the stages' sidecars (one BLAS thread per item).", "",
              card.markdown_table(["stage", "items", "seconds", "seconds per item"], timing), ""]
    write_bytes(ctx.stage_dir(NAME) / "README.md", "\n".join(lines).encode("utf-8"))


# Version 5: one item per figure, README.md written by finish.
STAGE = Stage(name=NAME, version=5, plan=plan, run=run, finish=finish)
