"""`meshsar bench pipeline --recipe`: one from-scratch build, where its time goes, as plain JSON."""

from __future__ import annotations

import json

import pytest

from meshsar_builder.bench.suite import bench_recipe
from meshsar_builder.cli import main
from meshsar_builder.pipeline.io import read_json

from .conftest import MANIFESTS


@pytest.mark.slow
def test_recipe_bench_accounts_for_the_build(tmp_path, capsys):
    (tmp_path / "pipeline-smoke" / "stale").mkdir(parents=True)  # a bench starts from scratch
    assert main(["bench", "pipeline", "--recipe", str(MANIFESTS / "smoke.toml"), "--workers", "2",
                 "--out", str(tmp_path)]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    result = read_json(tmp_path / "pipeline-smoke.json")
    assert printed["samples"] == result["samples"] == read_json(tmp_path / "pipeline-smoke" / "index.json")["n_samples"]
    assert not (tmp_path / "pipeline-smoke" / "stale").exists() and result["failures"] == []
    assert result["target_met"] is None  # 8 samples: not a paper-scale build
    stages = result["stages"]
    assert {"sources", "meshes", "remesh", "register", "ssm", "radar", "shards", "card"} <= set(stages)
    walls = sum(s["wall_seconds"] for s in stages.values())
    assert 0 < walls <= result["wall_seconds"] and result["outside_stages_seconds"] == pytest.approx(
        result["wall_seconds"] - walls)
    assert sum(s["share_of_wall"] for s in stages.values()) == pytest.approx(walls / result["wall_seconds"])
    # every pass's items: the register stage's groupwise rounds register each subject more than once
    register = read_json(tmp_path / "pipeline-smoke" / "register" / "groupwise.json")
    assert stages["register"]["items"] >= 3 and stages["register"]["item_seconds_sum"] > 0 and register
    radar = result["radar_seconds_summed"]
    assert radar["item_seconds"] == pytest.approx(stages["radar"]["item_seconds_sum"])
    assert 0 < radar["echo"] and 0 < radar["imaging"] and radar["rest"] >= 0
    assert result["peak_rss_mb_build"] > 50 and result["peak_rss_mb_largest_worker"] > 50


def test_recipe_goes_with_the_pipeline_part(capsys):
    assert main(["bench", "radar", "--recipe", str(MANIFESTS / "smoke.toml")]) == 2
    assert "--recipe goes with the pipeline part" in capsys.readouterr().err
