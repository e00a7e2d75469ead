"""Frames of one subject share one heart frame (DESIGN section 3), its ED (or first) frame's centre,
and one mesh: its reference frame's, fitted to each (stages/track.py)."""

from __future__ import annotations

import numpy as np

from meshsar_builder.geometry.meshfile import read_ply
from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.runner import build
from meshsar_builder.dataset.frames import merge_cycles, subject_series

BEATING = """
name = "beating"
seed = 0
[[sources]]
kind = "phantom"
anatomy = "biventricular"
subjects = 2
frames = 3
use = "direct"
[meshing]
spacing_mm = 2.0
sigma_mm = 1.5
[remesh]
edge_mm = 4.0
[radar]
aperture = [16, 16]
n_samples = 16
echo_decimation = [4, 4, 2]
views = ["anterior"]
[images]
size = 32
"""


def frame(source, subject, frame_no, phase=""):
    return {"source": source, "subject": subject, "frame": frame_no, "phase": phase}


def test_frames_are_in_cycle_order_and_the_reference_is_ed_else_the_first():
    records = {
        "a-f03": frame("a", "p1", 3), "a-f01": frame("a", "p1", 1), "a-f07": frame("a", "p1", 7, "ED"),
        "a-p2-f05": frame("a", "p2", 5), "a-p2-f02": frame("a", "p2", 2, "ES"),
        "b-f01": frame("b", "p1", 1),  # the same subject name in another source is another subject
        "c-ES": frame("c", "p3", None, "ES"), "c-ED": frame("c", "p3", None, "ED"),
        "still": frame("d", "s", None),
    }
    series = subject_series(records)
    assert series == [(["a-f01", "a-f03", "a-f07"], "a-f07"), (["a-p2-f02", "a-p2-f05"], "a-p2-f02"),
                      (["b-f01"], "b-f01"), (["c-ED", "c-ES"], "c-ED"), (["still"], "still")]
    # annotated (a) and predicted (b) frames of one cohort: one patient, one reference
    cohort = subject_series(records, {"a": "cohort", "b": "cohort"})
    assert (["a-f01", "b-f01", "a-f03", "a-f07"], "a-f07") in cohort


def test_frames_of_a_subject_are_scanned_in_its_ed_frame(tmp_path):
    recipe = tmp_path / "beating.toml"
    recipe.write_text(BEATING)
    out = tmp_path / "out"
    results = build(R.load(recipe), out, until="radar")
    assert results.failures == []
    remeshed, radar = results.of("remesh"), results.of("radar")
    subjects = {}
    for sid, rec in radar.items():
        subjects.setdefault(rec["meta"]["subject"], []).append(sid)
    assert len(subjects) == 2
    tracked = 0
    for sids in subjects.values():
        (ed,) = [s for s in sids if radar[s]["meta"]["phase"] == "ED"]
        centres = {s: np.load(out / "radar" / f"{s}.npz")["center_mm"] for s in sids}
        for s in sids:
            assert radar[s]["meta"]["reference_frame"] == ed
            np.testing.assert_allclose(centres[s], remeshed[ed]["center_mm"], atol=1e-4)
        # each frame's own box centre moves over the cycle (the base descends): the shared
        # centre is not just every frame's own
        own = np.array([remeshed[s]["center_mm"] for s in sids])
        assert np.ptp(own, axis=0).max() > 0.5
        # the frames are the ED mesh fitted to each (stages/track.py): one topology, one labelling;
        # a rejected fit leaves the frame its own mesh, said in its meta
        ref = read_ply(out / "track" / f"{ed}.ply")
        for s in sids:
            verts, faces, labels = read_ply(out / "track" / f"{s}.ply")
            kind = radar[s]["meta"]["correspondence"]
            if kind in ("reference", "tracked"):
                np.testing.assert_array_equal(faces, ref[1])
                np.testing.assert_array_equal(labels, ref[2])
                assert (kind == "reference") == (s == ed)
                assert s == ed or np.abs(verts - ref[0]).max() > 0.5  # and they move
            else:
                assert kind.startswith("own mesh (fit rejected: registration rejected: ")
                np.testing.assert_array_equal(faces, read_ply(out / "remesh" / f"{s}.ply")[1])
        tracked += sum(radar[s]["meta"]["correspondence"] == "tracked" for s in sids)
    assert tracked >= 2, "at most one frame of the two subjects was tracked"
    # one item per direction round the cycle from the reference; merged, every frame once
    references = {radar[sids[0]]["meta"]["reference_frame"] for sids in subjects.values()}
    assert set(results.of("track")) <= {f"{ref}-cycle-{way}" for ref in references for way in ("forward", "backward")}
    merged = merge_cycles(results.of("track").values())
    assert [m["reference"] for m in merged] == sorted(references)
    for m in merged:
        assert list(m["frames"]) == m["cycle"] and set(m["in_correspondence"]) <= set(m["cycle"])
