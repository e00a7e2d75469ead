"""The dataset card: the pictures and tables a researcher looks at before using a dataset.

Renders are off-screen (pyvista/VTK with EGL), with a parallel camera looking
along -w of each view and v up, scaled to the view's field of view, so a render
lines up pixel for pixel with the SAR images beside it.
"""

from __future__ import annotations

import os
from collections import defaultdict
from pathlib import Path

import numpy as np

# Off-screen VTK needs EGL where there is no display; set before pyvista loads VTK.
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from meshsar_builder.dataset.shards import INDEX_NAME, Shard  # noqa: E402
from meshsar_builder.geometry.landmarks import structure_name  # noqa: E402
from meshsar_builder.geometry.structures import STRUCTURES  # noqa: E402
from meshsar_builder.pipeline.io import atomic_path, read_json  # noqa: E402

# Canonical structure id -> colour (0: unlabelled).
PALETTE = np.array([
    [0.6, 0.6, 0.6], [0.85, 0.2, 0.2], [0.95, 0.6, 0.2], [0.2, 0.45, 0.85], [0.6, 0.3, 0.7],
    [0.3, 0.7, 0.8], [0.85, 0.4, 0.6], [0.45, 0.7, 0.3],
])


def render_views(verts: np.ndarray, faces: np.ndarray, labels: np.ndarray | None, views: list[dict],
                 fov_mm: float, size: int = 256) -> list[np.ndarray]:
    """One (size, size, 3) uint8 render per view, coloured by structure.

    verts : (n, 3) mm heart frame, faces : (m, 3), labels : (n,) uint8 or None,
    views : [{"u", "v", "w"}] unit vectors; the picture spans fov_mm like the SAR images.
    """
    import pyvista as pv

    mesh = pv.PolyData(np.asarray(verts, float), np.hstack([np.full((len(faces), 1), 3), faces]).ravel())
    colours = PALETTE[np.zeros(len(verts), int) if labels is None else np.minimum(labels, len(PALETTE) - 1)]
    mesh["rgb"] = (colours * 255).astype(np.uint8)
    out = []
    plotter = pv.Plotter(off_screen=True, window_size=(size, size))
    plotter.set_background("black")
    plotter.add_mesh(mesh, scalars="rgb", rgb=True, smooth_shading=True)
    plotter.enable_parallel_projection()
    for view in views:
        w, v = np.asarray(view["w"], float), np.asarray(view["v"], float)
        plotter.camera_position = [tuple(w * 1000.0), (0.0, 0.0, 0.0), tuple(v)]
        plotter.camera.parallel_scale = fov_mm / 2
        plotter.camera.clipping_range = (1.0, 3000.0)
        plotter.render()
        out.append(np.asarray(plotter.screenshot(return_img=True))[..., :3])
    plotter.close()
    return out


def save_figure(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, bbox_inches="tight")
    plt.close(fig)


def gallery(samples: list, index: dict, path: Path) -> None:
    """Per sample a row: for each view, the mesh render, then each SAR channel.

    samples : meshsar_builder.shards.Sample list; index : index.json object.
    """
    views, channels, fov = index["views"], index["channels"], index["fov_mm"]
    cols = len(views) * (1 + len(channels))
    fig, axes = plt.subplots(len(samples), cols, figsize=(1.6 * cols, 1.7 * len(samples)), squeeze=False)
    for r, s in enumerate(samples):
        renders = render_views(s.verts, s.faces, s.vert_labels, views, fov)
        for k, view in enumerate(views):
            base = k * (1 + len(channels))
            axes[r, base].imshow(renders[k])
            for c, name in enumerate(channels):
                signed = name == "depth"
                axes[r, base + 1 + c].imshow(s.sar[k, c].astype(np.float32), cmap="RdBu_r" if signed else "gray",
                                             vmin=-1 if signed else 0, vmax=1)
            if r == 0:
                axes[r, base].set_title(f"{view['name']}\nmesh", fontsize=8)
                for c, name in enumerate(channels):
                    axes[r, base + 1 + c].set_title(f"{view['name']}\n{name}", fontsize=8)
        # Horizontal, right of the margin: a vertical id is taller than its row and runs into the next.
        axes[r, 0].set_ylabel(s.sample_id, fontsize=7, rotation=0, ha="right", va="center")
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    handles = [Patch(color=PALETTE[i], label=name) for name, i in STRUCTURES.items()]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    save_figure(fig, path)


def speckle_figure(sample_id: str, stored: np.ndarray, specular: np.ndarray, views: list[dict],
                   cycle: list[tuple[str, np.ndarray]], path: Path) -> None:
    """The diffuse part at a glance: one sample's intensity with it and without, then one subject's speckle over its cycle.

    stored, specular : (V, H, W) intensity channels of the sample as built and re-rendered
    with the diffuse part off (same noise seeds); cycle : (frame label, (H, W) intensity of
    the first view) of a beating subject's frames, empty if there is none.
    """
    columns = max(2 * len(views), len(cycle))
    fig, axes = plt.subplots(2 if cycle else 1, columns, figsize=(1.7 * columns, 4.0 if cycle else 2.1),
                             squeeze=False)
    for k, view in enumerate(views):
        for j, (image, what) in enumerate(((stored[k], "specular + diffuse"), (specular[k], "specular only"))):
            axes[0, 2 * k + j].imshow(image, cmap="gray", vmin=0, vmax=1)
            axes[0, 2 * k + j].set_title(f"{view['name']}\n{what}", fontsize=7)
    axes[0, 0].set_ylabel(sample_id, fontsize=7)
    for ax, (label, image) in zip(axes[1] if cycle else [], cycle):
        ax.imshow(image, cmap="gray", vmin=0, vmax=1)
        ax.set_title(f"{views[0]['name']}, {label}", fontsize=7)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
        if not ax.images:
            ax.set_axis_off()
    save_figure(fig, path)


def ssm_variance_plot(report: dict, path: Path) -> None:
    """The standard SSM quality curves against the number of modes: variance explained per mode and
    cumulatively (compactness); generalisation and specificity (vertex to vertex, mm)."""
    var = np.asarray(report["variances_mm2"])
    frac = var / report["total_variance_mm2"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.2))
    modes = np.arange(1, len(var) + 1)
    a.bar(modes, frac * 100, color="0.6", label="per mode")
    a.plot(modes, np.asarray(report["compactness"]) * 100, "o-", color="C3", label="cumulative")
    a.set_xlabel("mode")
    a.set_ylabel("variance explained (%)")
    a.legend(fontsize=8)
    b.plot(modes, report["generalisation_mm"], "o-", color="C0", label="generalisation (leave-one-out)")
    b.plot(modes, report["specificity_curve_mm"], "s-", color="C2", label="specificity (nearest training shape)")
    b.set_xlabel("modes used")
    b.set_ylabel("vertex-to-vertex error (mm)")
    b.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def fitting_fov(shapes: list[np.ndarray], view: dict, fov_mm: float, margin: float = 1.05) -> float:
    """The field of view (mm) that shows every shape whole from `view`: at least fov_mm.

    shapes : list of (n, 3) mm, centred on the picture's centre; view : {"u", "v", ...}.
    """
    u, v = np.asarray(view["u"], float), np.asarray(view["v"], float)
    reach = max(float(np.abs(np.c_[verts @ u, verts @ v]).max()) for verts in shapes)
    return max(fov_mm, 2 * margin * reach)


def ssm_mode_strip(model, view: dict, fov_mm: float, path: Path, n_modes: int = 3) -> None:
    """Mean ± 3σ along the first modes, rendered from one view, all at one scale that shows each whole."""
    n_modes = min(n_modes, len(model.variances))
    steps = (-3.0, 0.0, 3.0)
    fig, axes = plt.subplots(n_modes, len(steps), figsize=(2.2 * len(steps), 2.2 * n_modes), squeeze=False)
    centre = (model.mean.min(axis=0) + model.mean.max(axis=0)) / 2
    shapes = {}
    for m in range(n_modes):
        for k in steps:
            coeffs = np.zeros(m + 1)
            coeffs[m] = k * np.sqrt(model.variances[m])
            shapes[m, k] = model.shape(coeffs) - centre
    fov_mm = fitting_fov(list(shapes.values()), view, fov_mm)
    for m in range(n_modes):
        for j, k in enumerate(steps):
            (img,) = render_views(shapes[m, k], model.faces, model.labels, [view], fov_mm)
            axes[m, j].imshow(img)
            axes[m, j].set_xticks([])
            axes[m, j].set_yticks([])
            axes[0, j].set_title(f"{k:+.0f} σ" if k else "mean", fontsize=9)
        axes[m, 0].set_ylabel(f"mode {m + 1}", fontsize=9)
    save_figure(fig, path)


def cycle_plot(frames: list[dict], path: Path) -> None:
    """Each dynamic subject over the cycle: chamber volumes (from label-map voxel counts) with
    the EF in the legend, and, where the records have them, the apex displacement and the
    base-plane descent from end-diastole (mm).

    frames : meshes-stage records with source, subject, cycle_fraction, phase,
        structure_volumes_ml, and optionally apex_mm (3,) and base_mm; frames whose
        cycle_fraction is unknown (no NbFrame) are left out.
    """
    fig, (ax, motion) = plt.subplots(1, 2, figsize=(10, 3.4))
    by_subject: dict[str, list[dict]] = {}
    for f in frames:
        if f["cycle_fraction"] is not None:
            by_subject.setdefault(f"{f['source']}/{f['subject']}", []).append(f)
    for i, (subject, recs) in enumerate(sorted(by_subject.items())):
        recs = sorted(recs, key=lambda f: f["cycle_fraction"])
        t = [f["cycle_fraction"] for f in recs]
        lv = np.array([f["structure_volumes_ml"].get("lv", 0.0) for f in recs])
        ef = f" EF {1 - lv.min() / lv.max():.2f}" if lv.max() > 0 else ""
        for name, ls in (("lv", "-"), ("rv", "--"), ("myo", ":")):
            ax.plot(t, [f["structure_volumes_ml"].get(name, 0.0) for f in recs], ls, color=f"C{i}",
                    label=f"{subject} {name.upper()}" + (ef if name == "lv" else ""))
        for f in recs:
            if f["phase"]:
                ax.annotate(f["phase"], (f["cycle_fraction"], f["structure_volumes_ml"].get("lv", 0.0)), fontsize=7)
        if all("apex_mm" in f for f in recs):
            ed = next((f for f in recs if f["phase"] == "ED"), recs[0])
            apex = np.linalg.norm(np.array([f["apex_mm"] for f in recs]) - ed["apex_mm"], axis=1)
            motion.plot(t, apex, "-", color=f"C{i}", label=f"{subject} apex displacement")
            motion.plot(t, [f["base_mm"] - ed["base_mm"] for f in recs], "--", color=f"C{i}",
                        label=f"{subject} base-plane descent")
    ax.set_xlabel("fraction of the cardiac cycle")
    ax.set_ylabel("volume (ml)")
    ax.legend(fontsize=6, ncol=2)
    motion.set_xlabel("fraction of the cardiac cycle")
    motion.set_ylabel("from end-diastole (mm)")
    if motion.lines:
        motion.legend(fontsize=6)
    fig.tight_layout()
    save_figure(fig, path)


def motion_plot(meshes: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], record: dict, path: Path) -> None:
    """One beating subject's per-vertex displacement over its cycle (stages/track.py).

    meshes : per frame id in cycle order, (verts (n, 3), faces, labels (n,)) from track/;
    record : the track stage's sidecar record of the subject (reference, frames).
    Left: the reference mesh's vertices seen from the front (x, z), coloured by their
    displacement at the frame that moved most; right: mean displacement per structure for
    every frame in correspondence (a frame whose fit was rejected has no point).
    """
    reference = record["reference"]
    ref_verts, _, ref_labels = meshes[reference]
    tracked = [mid for mid in meshes if record["frames"][mid].get("tracked")]
    moved = {mid: np.linalg.norm(meshes[mid][0] - ref_verts, axis=1) for mid in tracked}
    peak = max(moved, key=lambda mid: moved[mid].mean())
    fig, (ax, curve) = plt.subplots(1, 2, figsize=(10, 4))
    order = np.argsort(ref_verts[:, 1])  # nearer (smaller y, anterior) drawn last
    dots = ax.scatter(ref_verts[order, 0], ref_verts[order, 2], c=moved[peak][order], s=3, cmap="viridis")
    fig.colorbar(dots, ax=ax, label="displacement from the reference (mm)")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title(f"{peak} against {reference}", fontsize=8)
    position = {mid: i for i, mid in enumerate(meshes)}
    for structure in np.unique(ref_labels):
        if structure == 0:
            continue
        mine = ref_labels == structure
        xs = [position[mid] for mid in tracked]
        curve.plot(xs, [moved[mid][mine].mean() for mid in tracked], "o-", ms=3, label=structure_name(structure))
    curve.set_xlabel("frame (cycle order, from the series' first)")
    curve.set_ylabel("mean displacement (mm)")
    curve.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def gallery_ids(index: dict, n: int) -> list[str]:
    """The first samples of each subset, n in all, in dataset order."""
    by_subset = defaultdict(list)
    for sid, s in index["samples"].items():
        by_subset[s["subset"]].append(sid)
    per = -(-n // max(len(by_subset), 1))
    return [sid for ids in by_subset.values() for sid in ids[:per]][:n]


def load_samples(out: Path, index: dict, ids: list[str]) -> list:
    """The samples `ids` read from the shards of a built dataset (each shard opened once)."""
    shards = {}
    samples = []
    for sid in ids:
        k, row = index["samples"][sid]["shard"], index["samples"][sid]["row"]
        if k not in shards:
            shards[k] = Shard(out / index["shards"][k]["file"])
        samples.append(shards[k][row])
    return samples


def preview(out: Path, n: int) -> Path:
    """`meshsar preview`: a gallery of the first n samples of a built dataset, as card/preview.png."""
    index = read_json(out / INDEX_NAME)
    path = out / "card" / "preview.png"
    gallery(load_samples(out, index, gallery_ids(index, n)), index, path)
    return path


def markdown_table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)

