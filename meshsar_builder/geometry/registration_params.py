"""The recipe's [registration] section: the parameters of template registration.

Its own module so that nricp.py (the non-rigid fit), registration.py (which calls it) and
groupwise.py all import it from one place below them, with no import cycle among them.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RegistrationParams:
    """The recipe's [registration] section.

    template: "median" (the subject of median volume) or a subject id.
    template_vertices: vertex count the template surface is simplified to.
    max_mean_mm, max_p95_mm: acceptance thresholds of the two-sided surface distance.
    similarity: pre-align with scale (similarity) rather than rigid only.
    icp_points: surface points of the template used by the pre-alignment ICP.
    stiffness: NRICP stiffness per step (alpha of the second-order stiffness in nricp.py,
        with the template scaled to unit bounding-box diagonal), decreasing. It ends softer
        than Amberg's first-order schedule (0.05 to 0.002): a second difference penalises
        detail a few edges across far more than a first difference does.
    normal_weight: per step, exponent of the normal-agreement weight (cosine of the angle
        between the normals) of each match (0 switches it off); same length as stiffness.
    step_iterations: most iterations per stiffness step (fewer once the fit moves less
        than converge_mm).
    match_distance_mm: matches farther apart than this are ignored by the data term of
        that iteration.
    max_normal_deg: matches whose normals differ by more than this are ignored.
    gamma: weight of the translation part against the linear part in the stiffness term.
    reverse_weight: weight of the subject-to-template matches against the template-to-
        subject ones (0: one-sided, as in the paper).
    converge_mm: a step ends when the vertices moved less than this on average in an iteration.
    fold_retries: how often a stiffness step is repeated, stiffer at the vertices around faces
        that turned over or intersect, before the fit stops at the last fold-free step.
    fold_stiffening: factor on the stiffness of those vertices per repeat, and on the first-order
        (edge) term the guard switches on among them.
    distance_samples: area-weighted surface samples per side for the fit report.
    landmark_weight: weight of the label landmarks (see landmarks.py) in the first stiffness
        step, as a multiple of the data term's total weight shared among the landmarks; it
        decays with the stiffness (alpha / alpha_0), so the landmarks steer the coarse fit
        and leave the fine fit to the surface (Amberg's beta schedule). 0 switches them off.
        With 4 or more landmarks, the non-rigid fit starts from the template warped onto them
        by a thin-plate spline (tangential shape changes such as a twist are not recovered
        by closest-point matches, which only pull along the normal).
    landmark_smoothing: regulariser of that spline (see landmarks.landmark_warp).
    min_label_agreement: least fraction of each structure's template vertices that must
        land on their own structure (see landmarks.label_agreement) for acceptance.
    landmark_outlier_mm: a landmark is an inlier of the robust (least-median-of-squares)
        similarity fit between template and subject landmarks when within this, or 2.5 robust
        standard deviations (registration.robust_landmarks); the others are dropped, named in
        the report's landmarks_dropped.
    landmark_tolerance_mm: a fit whose mean landmark error exceeds that of its similarity
        start by more than this is retried without the landmarks it moved away (each by more
        than this), then rejected naming them.
    groupwise_rounds: most registrations to a groupwise template (the Procrustes mean of the
        previous round's fits, groupwise.py) after the first one to the reference subject;
        0 keeps the reference subject as the template.
    groupwise_converge_mm: the rounds stop early once the template moved less than this
        (mean vertex displacement from the previous template, after a rigid fit).
    divergence_growth: a fit is stopped at once (nricp.py) when the mean distance of its
        vertices to the subject grows past this factor times the least it reached (and by more
        than max_mean_mm), or when
    divergence_flipped: this fraction of its faces are turned over against the pre-aligned
        template; it is then retried from the similarity start (no spline) with every
        stiffness times retry_stiffening, then the softest step again, and the landmarks left
        out, and rejected with the figures if that diverges too (accept). A fit the fold guard
        stopped before the schedule's end is retried alike, and the retry kept if it fared better.
    retry_stiffening: see divergence_flipped.
    groupwise_max_distance_mm: a groupwise template (round >= 1) is checked against the fits
        it averages: a fit whose mean vertex distance from the mean (rigidly fitted, scale
        kept) exceeds this is left out and the mean made again (groupwise.mean_template).
        Real biventricular hearts of 200-735 ml lie 3.6-13.3 mm from their mean; runaway
        fits 50-360 mm.
    ring_points: landmarks along each junction ring besides its centre (landmarks.py; 0: none);
        they steer the thin-plate-spline start too.
    frame_ring_points: ring_points of a frame fit (tracking.py): the only cue to how far the
        walls moved along the surface (a base descending 12-15 mm in systole).
    frame_landmark_smoothing: landmark_smoothing of a frame fit. Each frame's landmarks miss their
        true places by 0.4-0.6 mm (up to 1.9), a warm start carries the last frame's miss into the next, and a
        spline at smoothing 10 sends that miss to a wall 24 mm from the nearest landmark about 5 times over: under
        a known motion of a real biventricular surface the far RV end reached 5.3 mm of error for 4.7 mm of
        motion by mid-cycle (0.02 mm from the surface, so accepted). At 100: 3.2 mm, and the mean error of the
        cycle lower on every surface and motion tried (docs/registration.md).
    frame_min_label_agreement: min_label_agreement of a frame fit. A short-axis union surface's
        LV patch is the blood pool at the base, not tissue: over the demo phantom's cycle it
        shrinks to 41 % of its ED area as the wall thickens, its border sliding over the
        tissue, and fits 0.04-0.06 mm from every frame kept 0.954-0.970 of it (half the frames
        fell under 0.97).
    frame_steps: how many of the softest stiffness steps a frame of a beating subject runs when
        fitted by its reference frame's mesh, warm-started from its neighbour's fit (tracking.py).
    groupwise_smoothing: most Taubin steps on a groupwise template to clear self-
        intersections and flipped faces of the plain mean before the round fails.
    coarse_steps: how many of the stiffest stiffness steps (at most all but the last) run on the
        template simplified to coarse_vertices vertices, whose transforms then start the rest
        at full resolution (nricp._coarse_start); only for templates of at least twice
        coarse_vertices; 0: none. Default 1: the first step coarse cost 0.005 mm of
        correspondence on the phantom heart's known warps on average, the second coarse as
        well up to 0.09 mm more (twist).
    round_coarse_steps: coarse_steps of a groupwise round before the last (groupwise.py). Those
        fits only make the next round's template, a mean whose movement is judged against
        groupwise_converge_mm (0.5 mm), so they can afford the correspondence the coarse
        steps cost; all but the softest step coarse reach the subject as closely (0.071 against
        0.070 mm on a demo heart) in half the time.
    """

    template: str = "median"
    template_vertices: int = 6000
    max_mean_mm: float = 0.5
    max_p95_mm: float = 1.5
    similarity: bool = True
    icp_points: int = 3000
    stiffness: tuple[float, ...] = (0.05, 0.02, 0.005, 0.001, 0.0002)
    normal_weight: tuple[float, ...] = (0.5, 0.5, 0.5, 0.0, 0.0)
    step_iterations: int = 10
    match_distance_mm: float = 10.0
    max_normal_deg: float = 60.0
    gamma: float = 1.0
    reverse_weight: float = 0.1
    converge_mm: float = 0.02
    fold_retries: int = 4
    fold_stiffening: float = 10.0
    distance_samples: int = 20000
    landmark_weight: float = 0.1
    landmark_smoothing: float = 10.0
    min_label_agreement: float = 0.97
    groupwise_rounds: int = 2
    groupwise_converge_mm: float = 0.5
    groupwise_smoothing: int = 10
    landmark_outlier_mm: float = 5.0
    landmark_tolerance_mm: float = 2.0
    divergence_growth: float = 1.5
    divergence_flipped: float = 0.01
    retry_stiffening: float = 4.0
    groupwise_max_distance_mm: float = 25.0
    frame_steps: int = 2
    frame_landmark_smoothing: float = 100.0
    frame_min_label_agreement: float = 0.95
    ring_points: int = 0
    frame_ring_points: int = 8
    coarse_steps: int = 1
    coarse_vertices: int = 1500
    round_coarse_steps: int = 4

    def __post_init__(self) -> None:
        if not self.template:
            raise ValueError(f"template: must be 'median' or a subject id, got {self.template!r}")
        if self.template_vertices < 100:
            raise ValueError(f"template_vertices: must be >= 100, got {self.template_vertices}")
        if not self.max_mean_mm > 0:
            raise ValueError(f"max_mean_mm: must be > 0, got {self.max_mean_mm}")
        if not self.max_p95_mm > 0:
            raise ValueError(f"max_p95_mm: must be > 0, got {self.max_p95_mm}")
        if self.icp_points < 10:
            raise ValueError(f"icp_points: must be >= 10, got {self.icp_points}")
        if not self.stiffness or any(not s > 0 for s in self.stiffness):
            raise ValueError(f"stiffness: must be a non-empty list of values > 0, got {self.stiffness}")
        if len(self.normal_weight) != len(self.stiffness) or any(w < 0 for w in self.normal_weight):
            raise ValueError(
                f"normal_weight: must hold {len(self.stiffness)} values >= 0 (one per stiffness step), "
                f"got {self.normal_weight}"
            )
        if self.step_iterations < 1:
            raise ValueError(f"step_iterations: must be >= 1, got {self.step_iterations}")
        if not self.match_distance_mm > 0:
            raise ValueError(f"match_distance_mm: must be > 0, got {self.match_distance_mm}")
        if not 0 < self.max_normal_deg <= 180:
            raise ValueError(f"max_normal_deg: must be in (0, 180], got {self.max_normal_deg}")
        if not self.gamma > 0:
            raise ValueError(f"gamma: must be > 0, got {self.gamma}")
        if not self.reverse_weight >= 0:
            raise ValueError(f"reverse_weight: must be >= 0, got {self.reverse_weight}")
        if not self.converge_mm > 0:
            raise ValueError(f"converge_mm: must be > 0, got {self.converge_mm}")
        if self.fold_retries < 0:
            raise ValueError(f"fold_retries: must be >= 0, got {self.fold_retries}")
        if not self.fold_stiffening > 1:
            raise ValueError(f"fold_stiffening: must be > 1, got {self.fold_stiffening}")
        if not self.landmark_weight >= 0:
            raise ValueError(f"landmark_weight: must be >= 0, got {self.landmark_weight}")
        for key in ("landmark_smoothing", "frame_landmark_smoothing"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"{key}: must be >= 0, got {getattr(self, key)}")
        if not 0 <= self.min_label_agreement <= 1:
            raise ValueError(f"min_label_agreement: must be in [0, 1], got {self.min_label_agreement}")
        if self.groupwise_rounds < 0:
            raise ValueError(f"groupwise_rounds: must be >= 0, got {self.groupwise_rounds}")
        if not self.groupwise_converge_mm >= 0:
            raise ValueError(f"groupwise_converge_mm: must be >= 0, got {self.groupwise_converge_mm}")
        if self.groupwise_smoothing < 0:
            raise ValueError(f"groupwise_smoothing: must be >= 0, got {self.groupwise_smoothing}")
        if not self.landmark_outlier_mm > 0:
            raise ValueError(f"landmark_outlier_mm: must be > 0, got {self.landmark_outlier_mm}")
        if not self.landmark_tolerance_mm > 0:
            raise ValueError(f"landmark_tolerance_mm: must be > 0, got {self.landmark_tolerance_mm}")
        if not self.divergence_growth > 1:
            raise ValueError(f"divergence_growth: must be > 1, got {self.divergence_growth}")
        if not 0 < self.divergence_flipped <= 1:
            raise ValueError(f"divergence_flipped: must be in (0, 1], got {self.divergence_flipped}")
        if not self.retry_stiffening >= 1:
            raise ValueError(f"retry_stiffening: must be >= 1, got {self.retry_stiffening}")
        if not self.groupwise_max_distance_mm > 0:
            raise ValueError(f"groupwise_max_distance_mm: must be > 0, got {self.groupwise_max_distance_mm}")
        if not 1 <= self.frame_steps <= len(self.stiffness):
            raise ValueError(f"frame_steps: must be in [1, {len(self.stiffness)}] (the stiffness steps), "
                             f"got {self.frame_steps}")
        if not 0 <= self.frame_min_label_agreement <= 1:
            raise ValueError(f"frame_min_label_agreement: must be in [0, 1], got {self.frame_min_label_agreement}")
        for key in ("ring_points", "frame_ring_points"):
            if getattr(self, key) < 0:
                raise ValueError(f"{key}: must be >= 0, got {getattr(self, key)}")
        for key in ("coarse_steps", "round_coarse_steps"):
            if getattr(self, key) < 0:
                raise ValueError(f"{key}: must be >= 0, got {getattr(self, key)}")
        if self.coarse_vertices < 100:
            raise ValueError(f"coarse_vertices: must be >= 100, got {self.coarse_vertices}")
        if self.distance_samples < 100:
            raise ValueError(f"distance_samples: must be >= 100, got {self.distance_samples}")
