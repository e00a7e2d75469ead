"""Recipe validation: every malformed recipe names the file and the key."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from meshsar_builder.pipeline import recipe as R
from meshsar_builder.pipeline.errors import RecipeError

from .conftest import MANIFESTS

MINIMAL = 'name = "t"\n[[sources]]\nkind = "phantom"\nsubjects = 2\n'


@pytest.mark.parametrize("path", sorted(MANIFESTS.glob("*.toml")), ids=lambda p: p.name)
def test_shipped_recipes_load(path):
    r = R.load(path)
    assert r.name == path.stem and r.sources
    assert r.sha256 and r.text == path.read_text()


def test_defaults_resolved():
    r = R.parse(MINIMAL + '[[sources]]\nkind = "phantom"\nanatomy = "biventricular"\nsubjects = 1\n')
    wh, bv = r.sources
    assert (wh.name, wh.use, wh.voxel_mm) == ("phantom_wh", "ssm", (1.0, 1.0, 1.0))
    assert (bv.name, bv.use, bv.voxel_mm, bv.structures) == ("phantom_bv", "direct", (1.5, 1.5, 8.0), ("lv", "myo", "rv"))
    assert r.meshing.spacing_mm == 1.0 and r.shards.shard_size == 64
    assert r.splits.ratios == {"train": 0.8, "test": 0.2}


@pytest.mark.parametrize(
    "body, message",
    [
        (MINIMAL + "[meshing]\nspacing = 1.0\n", r"\[meshing\]: unknown key 'spacing'"),
        (MINIMAL + '[meshing]\nspacing_mm = "one"\n', r"\[meshing\] spacing_mm: expected a number, got 'one'"),
        (MINIMAL + "[meshing]\nspacing_mm = -1.0\n", r"\[meshing\] spacing_mm: must be > 0"),
        (MINIMAL + "[shards]\nshard_size = 0\n", r"\[shards\] shard_size: must be >= 1"),
        (MINIMAL + "[shards]\nshard_size = 2.5\n", r"\[shards\] shard_size: expected an integer"),
        (MINIMAL + "colour = 1\n", r"unknown key 'colour'"),
        ("seed = -5\n" + MINIMAL, r"seed: must be >= 0 \(numpy's seed sequences take non-negative integers\), got -5"),
        ('[[sources]]\nkind = "phantom"\nsubjects = 2\n', r"missing required key 'name'"),
        ('name = "t"\n', r"missing required key 'sources'"),
        ('name = "t"\n[[sources]]\nsubjects = 2\n', r"\[\[sources\]\] #1: missing required key 'kind'"),
        ('name = "t"\n[[sources]]\nkind = "dicom"\n', r"#1 kind: must be one of"),
        ('name = "t"\n[[sources]]\nkind = "phantom"\n', r"#1 subjects: a phantom source needs subjects >= 1"),
        (MINIMAL + '[[sources]]\nkind = "phantom"\nsubjects = 1\n', r"'phantom_wh' used twice"),
        ('name = "t"\n[[sources]]\nkind = "nifti"\npath = "x"\n', r"#1 labels: a nifti source needs a label table"),
        ('name = "t"\n[[sources]]\nkind = "nifti"\npath = "x"\nlabels = { heart = 1 }\n', r"labels: unknown structures \['heart'\]"),
        ('name = "t"\n[[sources]]\nkind = "acdc"\nstructures = ["la"]\n', r"structures: \['la'\] not in this source's"),
        (MINIMAL.replace("subjects = 2", "subjects = 2\nvoxel_mm = [1.0, 0.0, 1.0]"), r"voxel_mm: three positive sizes"),
        ('name = "a b"\n[[sources]]\nkind = "phantom"\nsubjects = 1\n', r"name: letters, digits"),
        ('name = "t"\n[[sources]\n', r"not valid TOML"),
        (MINIMAL + '[splits]\nratios = { train = "most" }\n', r"\[splits\] ratios.train: expected a number"),
        ('name = "t"\n[[sources]]\nkind = "mmwhs"\npattern = "*_label.nii.gz"\n', r"#1 pattern: only a nifti source"),
        ('name = "t"\n[[sources]]\nkind = "nifti"\nlabels = { lv = 1 }\npattern = "*.png"\n', r"#1 pattern: must match NIfTI files"),
        (MINIMAL.replace("subjects = 2", "subjects = 2\nrequire_affine = true"), r"#1 require_affine: only a label-map source"),
        ('name = "t"\n[[sources]]\nkind = "acdc"\nrequire_affine = 1\n', r"#1 require_affine: expected true or false"),
        ('name = "t"\n[[sources]]\nkind = "shape_model"\nmean = "m.vtk"\nvariances = "v.csv"\nsamples = 2\nstructures = ["lv"]\n', r"#1 modes: a shape_model source needs mean, modes and variances"),
        ('name = "t"\n[[sources]]\nkind = "shape_model"\nmean = "m.vtk"\nvariances = "v.csv"\nmodes = "c.csv.gz"\nstructures = ["lv"]\n', r"#1 samples: a shape_model source needs samples >= 1"),
        ('name = "t"\n[[sources]]\nkind = "shape_model"\nmean = "m.vtk"\nvariances = "v.csv"\nmodes = "c.csv.gz"\nsamples = 2\n', r"#1 structures: a shape_model without vertex_labels is one structure"),
        ('name = "t"\n[[sources]]\nkind = "shape_model"\nmean = "m.vtk"\nvariances = "v.csv"\nmodes = "c.csv.gz"\nsamples = 2\nvertex_labels = "l.csv"\n', r"#1 vertex_labels: needs a label table"),
        ('name = "t"\n[[sources]]\nkind = "shape_model"\nmean = "m.vtk"\nvariances = "v.csv"\nmodes = "c.csv.gz"\nsamples = 2\nstructures = ["lv"]\nlabels = { lv = 1 }\n', r"#1 labels: a shape_model's label table maps"),
        ('name = "t"\n[[sources]]\nkind = "shape_model"\nmean = "m.vtk"\nvariances = "v.csv"\nmodes = "c.csv.gz"\nsamples = 2\nstructures = ["lv"]\nuse = "direct"\n', r"#1 use: a shape_model source gives samples"),
        ('name = "t"\n[[sources]]\nkind = "shape_model"\nmean = "m.vtk"\nvariances = "v.csv"\nmodes = "c.csv.gz"\nsamples = 2\nstructures = ["lv"]\nn_modes = -1\n', r"#1 n_modes: must be >= 0"),
        ('name = "t"\n[[sources]]\nkind = "acdc"\nmean = "m.vtk"\n', r"#1 mean: only a shape_model source takes mean"),
        (MINIMAL + "[meshing]\nvessel_length_mm = { heart = 30 }\n", r"\[meshing\] vessel_length_mm: unknown vessel 'heart'"),
        (MINIMAL + "[meshing]\nvessel_length_mm = { aorta = -5 }\n", r"\[meshing\] vessel_length_mm: aorta must be in \(0, 1000\) mm"),
        (MINIMAL + '[meshing]\nvessel_length_mm = { pa = "long" }\n', r"\[meshing\] vessel_length_mm.pa: expected a number"),
        (MINIMAL + '[radar]\ndevice = "gpu"\n', r'\[radar\] device: must be "cpu", "cuda" or "cuda:N"'),
        (MINIMAL + '[radar]\ndevice = "cuda:x"\n', r'\[radar\] device: must be "cpu", "cuda" or "cuda:N"'),
        (MINIMAL + '[radar]\ndevice = 0\n', r"\[radar\] device: expected a string"),
    ],
)
def test_malformed_recipe_names_file_and_key(tmp_recipe, body, message):
    path = tmp_recipe(body, "bad.toml")
    with pytest.raises(RecipeError, match=message) as err:
        R.load(path)
    assert str(path) in str(err.value)


def test_data_path_uses_meshsar_data(monkeypatch, tmp_path):
    r = R.parse('name = "t"\n[[sources]]\nkind = "mmwhs"\npath = "MM-WHS"\n')
    monkeypatch.delenv("MESHSAR_DATA", raising=False)
    assert str(r.sources[0].data_path()) == "MM-WHS"
    monkeypatch.setenv("MESHSAR_DATA", str(tmp_path))
    assert r.sources[0].data_path() == tmp_path / "MM-WHS"
    no_path = R.parse('name = "t"\n[[sources]]\nkind = "acdc"\n').sources[0]
    assert no_path.data_path() == tmp_path
    monkeypatch.delenv("MESHSAR_DATA")
    with pytest.raises(RecipeError, match="MESHSAR_DATA is not set"):
        no_path.data_path()


toml_scalars = st.one_of(
    st.booleans(), st.integers(-5, 200), st.floats(-10, 1e4, allow_nan=False),
    st.text("abcxyz_ ", max_size=6), st.lists(st.integers(0, 9), max_size=3),
)


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v + '"'
    if isinstance(v, list):
        return "[" + ", ".join(map(str, v)) + "]"
    return repr(v)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    section=st.sampled_from(sorted(R.SECTIONS)),
    entries=st.dictionaries(
        st.sampled_from(["spacing_mm", "sigma_mm", "edge_mm", "samples", "variance", "shard_size", "seed", "vessel_length_mm",
                         "views", "step_mm", "aperture", "size", "fov_mm", "window", "bogus"]),
        toml_scalars, max_size=3,
    ),
)
def test_any_section_content_parses_or_raises_recipe_error(section, entries):
    body = MINIMAL + f"[{section}]\n" + "".join(f"{k} = {toml_value(v)}\n" for k, v in entries.items())
    try:
        r = R.parse(body, "fuzz.toml")
    except RecipeError as e:
        assert str(e).startswith("fuzz.toml: ")
    else:
        assert getattr(r, section) is not None


@settings(max_examples=120, deadline=None)
@given(
    entries=st.dictionaries(
        st.sampled_from(["mean", "modes", "variances", "vertex_labels", "samples", "n_modes", "structures", "use",
                         "pattern", "require_affine", "subjects"]),
        st.one_of(toml_scalars, st.sampled_from(['"m.vtk"', '["lv"]', '["lv", "rv"]', '"ssm"', '"direct"'])),
        max_size=6,
    ),
    kind=st.sampled_from(["shape_model", "nifti", "acdc"]),
)
def test_any_source_entry_parses_or_raises_recipe_error(entries, kind):
    literal = lambda v: isinstance(v, str) and v[:1] in ('"', "[")  # noqa: E731 (already TOML)
    lines = "".join(f"{k} = {v if literal(v) else toml_value(v)}\n" for k, v in entries.items())
    body = f'name = "t"\n[[sources]]\nkind = "{kind}"\n' + ('labels = { lv = 1 }\n' if kind == "nifti" else "") + lines
    try:
        r = R.parse(body, "fuzz.toml")
    except RecipeError as e:
        assert str(e).startswith("fuzz.toml: ")
    else:
        (spec,) = r.sources
        if spec.kind == "shape_model":
            assert spec.samples >= 1 and spec.mean and spec.modes and spec.variances and spec.use == "ssm"


def test_radar_device_from_the_recipe_or_the_command_line():
    assert R.parse(MINIMAL).radar.device == "cpu"
    assert R.parse(MINIMAL + '[radar]\ndevice = "cuda:1"\n').radar.device == "cuda:1"
    recipe = R.parse(MINIMAL)
    changed = R.override(recipe, "radar", "device", "cuda", "--device")
    # only that key changes; the recipe's text and digest stay the file's
    assert changed.radar == dataclasses.replace(recipe.radar, device="cuda") and recipe.radar.device == "cpu"
    assert (changed.text, changed.sha256, changed.meshing) == (recipe.text, recipe.sha256, recipe.meshing)
    with pytest.raises(RecipeError, match=r'^--device: device: must be "cpu", "cuda" or "cuda:N".*\'tpu\''):
        R.override(recipe, "radar", "device", "tpu", "--device")
    with pytest.raises(RecipeError, match=r"--device: expected a string"):
        R.override(recipe, "radar", "device", 1, "--device")
