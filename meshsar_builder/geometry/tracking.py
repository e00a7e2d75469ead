"""Frames of a beating subject in correspondence: each frame fitted by its reference frame's mesh.

A dynamic subject's frames (a cine series) are meshed one by one, so two frames share no
vertices. Here the reference frame's remeshed surface (its ED frame, else its first) is the
subject's template, and every other frame is fitted by it with the project's label-aware
registration (registration.register), warm-started from the fit of the frame next to it
toward the reference: frames are visited outward from the reference, forward to the end of
the series and backward to its start. The frames lie in one scanner frame, so a fit starts
where its neighbour's ended with no pre-alignment (a similarity would take up contraction
and twist, which are shape), and runs only the softest `frame_steps` of the stiffness
schedule (the motion between neighbouring frames is small); one outside the thresholds (accept,
with frame_min_label_agreement: a blood-pool patch is not tissue) is tried once more with
the whole schedule (a large jump, as between an ED and an ES frame alone), and if that fails
too it leaves that frame with its own mesh, recorded, and the next frame starts from the
last accepted fit.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence

import numpy as np

from meshsar_builder.geometry.registration import accept, register
from meshsar_builder.geometry.registration_params import RegistrationParams
from meshsar_builder.pipeline.errors import MeshError


def frame_params(params: RegistrationParams, steps: int | None = None) -> RegistrationParams:
    """The registration parameters of a warm-started frame fit: the softest `steps` (default
    frame_steps) stiffness steps of the schedule (and their normal weights), with
    frame_ring_points points along each junction ring as landmarks, their spline smoothed by
    frame_landmark_smoothing, judged on frame_min_label_agreement; at full resolution unless
    they are the whole schedule (the soft steps have nothing to coarsen)."""
    k = params.frame_steps if steps is None else steps
    return dataclasses.replace(params, stiffness=params.stiffness[-k:], normal_weight=params.normal_weight[-k:],
                               ring_points=params.frame_ring_points, landmark_smoothing=params.frame_landmark_smoothing,
                               coarse_steps=params.coarse_steps if k == len(params.stiffness) else 0,
                               min_label_agreement=params.frame_min_label_agreement)


def visit_chains(n_frames: int, reference: int) -> list[list[tuple[int, int]]]:
    """The (frame, neighbour it starts from) pairs of each direction, outward from the reference
    around the cycle (a cine series is periodic: its last frame neighbours its first), so no
    frame is more than half a cycle of warm starts from the reference (drift grows with each).

    [forward, backward], an empty one left out. The two share only the reference, so they
    can be fitted side by side (stages/track.py: one item each).
    """
    forward = n_frames // 2  # of the other n - 1 frames; the extra one of an even count goes forward
    chains = [[((reference + k) % n_frames, (reference + k - 1) % n_frames) for k in range(1, forward + 1)],
              [((reference - k) % n_frames, (reference - k + 1) % n_frames) for k in range(1, n_frames - forward)]]
    return [chain for chain in chains if chain]


def visit_order(n_frames: int, reference: int) -> list[tuple[int, int]]:
    """Both chains of visit_chains, forward first."""
    return [pair for chain in visit_chains(n_frames, reference) for pair in chain]


def track_frames(
    frames: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    reference: int,
    params: RegistrationParams,
    rng_for: Callable[[int], np.random.Generator],
    order: Sequence[tuple[int, int]] | None = None,
) -> tuple[list[np.ndarray | None], list[dict]]:
    """Fit every frame of one subject with its reference frame's mesh.

    frames : per frame (verts (p, 3) float mm, faces (q, 3) int, labels (p,) int), in cycle
    order, all in one scanner frame; reference : index of the template frame;
    rng_for : frame index -> its generator (the fit report's surface samples); order : the
    (frame, neighbour) pairs to fit, default visit_order (every frame; one chain of
    visit_chains fits that direction alone, to the same result).
    Returns per frame the fitted vertices (n, 3) (faces and labels are the reference's), or
    None where the fit was rejected or not asked for (an empty report), and per frame a report (JSON-ready): `tracked`, `from`
    (the frame index the fit started from), `seconds`, the fit's figures (mean_mm, p95_mm,
    label_agreement, landmark_error_mm, nricp; of the last attempt), `stiffness_steps` of the
    schedule that was accepted and, for a rejected fit, `rejected` (the reason).
    """
    template_verts, template_faces, template_labels = frames[reference]
    fits: list[np.ndarray | None] = [None] * len(frames)
    fits[reference] = np.asarray(template_verts, dtype=np.float64)
    reports: list[dict] = [{}] * len(frames)
    reports[reference] = {"tracked": True, "reference": True}
    order = visit_order(len(frames), reference) if order is None else list(order)
    chain = {reference: [reference]}  # each frame's warm-start chain back to the reference
    for index, neighbour in order:
        chain[index] = [index, *chain[neighbour]]
    for index, neighbour in order:
        # The last accepted fit toward the reference: a rejected neighbour is skipped over.
        start = next(j for j in chain[neighbour] if fits[j] is not None)
        verts, faces, labels = frames[index]
        began = time.perf_counter()
        summary: dict = {"tracked": False, "from": start}
        # The soft steps follow a neighbour's small motion; a fit they leave outside the
        # thresholds (a large jump: an ED and an ES frame only) is tried once more with the
        # whole stiffness schedule.
        for steps in dict.fromkeys((params.frame_steps, len(params.stiffness))):
            fit_params = frame_params(params, steps)
            try:  # an invalid frame mesh (register) or a fit outside the thresholds (accept)
                fitted, report = register(fits[start], template_faces, verts, faces, fit_params, rng_for(index),
                                          template_labels, labels, prealigned=True)
                summary |= {k: report[k] for k in ("mean_mm", "p95_mm", "label_agreement", "landmark_error_mm", "nricp")
                            if k in report}
                accept(report, fit_params)
            except MeshError as e:
                summary["rejected"] = str(e)
                if "registration subject" in summary["rejected"]:
                    break  # the frame's own mesh is invalid: no schedule can fit it
                continue
            fits[index] = fitted
            summary.pop("rejected", None)
            summary.update(tracked=True, stiffness_steps=steps)
            break
        reports[index] = {**summary, "seconds": round(time.perf_counter() - began, 3)}
    return fits, reports
