"""Dataset recipes (TOML): parsed into frozen dataclasses, validated on load.

Each recipe table is the parameter dataclass of the library module that uses
it, so a key's name, type and default live in one place. Unknown keys, wrong
types, missing required keys and impossible values raise RecipeError naming
the file and the key.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import os
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from .errors import RecipeError
from .sources import STRUCTURES

# Recipe table -> the dataclass that defines its keys (imported lazily: the
# splits and verify commands should not pay for trimesh or torch).
SECTIONS: dict[str, str] = {
    "meshing": "meshsar_builder.meshing:MeshingParams",
    "remesh": "meshsar_builder.remesh:RemeshParams",
    "registration": "meshsar_builder.registration:RegistrationParams",
    "ssm": "meshsar_builder.ssm:SSMParams",
    "radar": "meshsar_builder.radar:RadarParams",
    "images": "meshsar_builder.sar:ImageParams",
    "shards": "meshsar_builder.recipe:ShardParams",
    "splits": "meshsar_builder.recipe:SplitParams",
}

KINDS = ("phantom", "mmwhs", "acdc", "nifti")
SOURCE_STRUCTURES = {
    "mmwhs": ("lv", "myo", "rv", "la", "ra", "aorta", "pa"),
    "acdc": ("lv", "myo", "rv"),
}
NAME_RE = re.compile(r"^[A-Za-z0-9_-]+$")


@dataclass(frozen=True)
class ShardParams:
    shard_size: int = 64

    def __post_init__(self):
        if self.shard_size < 1:
            raise ValueError(f"shard_size: must be >= 1, got {self.shard_size}")


@dataclass(frozen=True)
class SplitParams:
    seed: int = 0
    ratios: dict[str, float] = field(default_factory=lambda: {"train": 0.8, "test": 0.2})
    group_by: str = "subject"

    def __post_init__(self):
        from .splits import GROUP_BY, check_ratios

        check_ratios(self.ratios)
        if self.group_by not in GROUP_BY:
            raise ValueError(f"group_by: must be one of {GROUP_BY}, got {self.group_by!r}")


@dataclass(frozen=True)
class SourceSpec:
    """One [[sources]] entry. Empty strings / zero mean 'the default for this kind'."""

    kind: str
    name: str = ""  # default: phantom_wh / phantom_bv / mmwhs / acdc / nifti
    anatomy: str = "whole_heart"  # phantom only: whole_heart | biventricular
    subjects: int = 0  # phantom: how many to generate; real data: at most this many (0 = all)
    frames: int = 20  # phantom biventricular: frames per cycle
    voxel_mm: tuple[float, ...] = ()  # phantom: voxel size; default 1 mm (whole heart) or 1.5x1.5x8 (ACDC-like)
    path: str = ""  # real data folder; relative paths are under $MESHSAR_DATA when set
    labels: dict[str, int] = field(default_factory=dict)  # nifti: structure name -> label value
    structures: tuple[str, ...] = ()  # meshed union; default: every structure the source has
    use: str = ""  # ssm | direct; default: ssm for whole-heart sources, direct otherwise

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind: must be one of {KINDS}, got {self.kind!r}")
        if self.anatomy not in ("whole_heart", "biventricular"):
            raise ValueError(f"anatomy: must be whole_heart or biventricular, got {self.anatomy!r}")
        biv = self.kind == "acdc" or (self.kind == "phantom" and self.anatomy == "biventricular")
        whole = self.kind == "mmwhs" or (self.kind == "phantom" and self.anatomy == "whole_heart")
        default_name = {"phantom": "phantom_wh" if whole else "phantom_bv"}.get(self.kind, self.kind)
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen: resolve defaults once)
        set_("name", self.name or default_name)
        if not NAME_RE.match(self.name):
            raise ValueError(f"name: letters, digits, '_' and '-' only, got {self.name!r}")
        if self.kind == "phantom" and self.subjects < 1:
            raise ValueError(f"subjects: a phantom source needs subjects >= 1, got {self.subjects}")
        if self.subjects < 0:
            raise ValueError(f"subjects: must be >= 0, got {self.subjects}")
        if self.frames < 2:
            raise ValueError(f"frames: must be >= 2, got {self.frames}")
        if self.voxel_mm and (len(self.voxel_mm) != 3 or min(self.voxel_mm) <= 0):
            raise ValueError(f"voxel_mm: three positive sizes, got {list(self.voxel_mm)}")
        if self.kind != "phantom":
            if self.voxel_mm:
                raise ValueError("voxel_mm: only a phantom source takes a voxel size")
        else:
            set_("voxel_mm", tuple(self.voxel_mm or ((1.0, 1.0, 1.0) if whole else (1.5, 1.5, 8.0))))
        if self.kind == "nifti" and not self.labels:
            raise ValueError("labels: a nifti source needs a label table, e.g. { lv = 1, myo = 2, rv = 3 }")
        if self.labels and self.kind != "nifti":
            raise ValueError(f"labels: only a nifti source takes a label table ({self.kind} has a fixed one)")
        bad = sorted(set(self.labels) - set(STRUCTURES))
        if bad:
            raise ValueError(f"labels: unknown structures {bad}; known: {sorted(STRUCTURES)}")
        available = tuple(self.labels) if self.kind == "nifti" else SOURCE_STRUCTURES["acdc" if biv else "mmwhs"]
        bad = sorted(set(self.structures) - set(available))
        if bad:
            raise ValueError(f"structures: {bad} not in this source's structures {list(available)}")
        set_("structures", tuple(self.structures or available))
        set_("use", self.use or ("ssm" if whole else "direct"))
        if self.use not in ("ssm", "direct"):
            raise ValueError(f"use: must be 'ssm' or 'direct', got {self.use!r}")

    @property
    def subset(self) -> str:
        """The dataset subset a source feeds: SSM-sampled whole heart, or dynamic/direct meshes."""
        return "ssm" if self.use == "ssm" else "direct"

    def data_path(self) -> Path:
        """The real-data folder: `path`, under $MESHSAR_DATA when relative and that is set."""
        root = os.environ.get("MESHSAR_DATA", "")
        if not self.path and not root:
            raise RecipeError(f"[[sources]] {self.name}: path: not given and MESHSAR_DATA is not set")
        p = Path(self.path) if self.path else Path(root)
        return p if p.is_absolute() or not root else Path(root) / p


@dataclass(frozen=True)
class Recipe:
    name: str
    seed: int
    sources: tuple[SourceSpec, ...]
    sections: dict[str, Any]  # table name -> its parameter dataclass instance
    file: str = ""
    sha256: str = ""
    text: str = ""

    def __getattr__(self, key: str) -> Any:
        # recipe.meshing, recipe.radar, ...: the sections by name
        sections = self.__dict__.get("sections", {})
        if key in sections:
            return sections[key]
        raise AttributeError(key)

    def as_dict(self) -> dict:
        """Plain data of the parsed recipe (defaults filled in), for JSON sidecars and the index."""
        return {
            "name": self.name,
            "seed": self.seed,
            "sources": [dataclasses.asdict(s) for s in self.sources],
            **{k: dataclasses.asdict(v) for k, v in self.sections.items()},
        }


def section_class(name: str) -> type:
    module, cls = SECTIONS[name].split(":")
    return getattr(importlib.import_module(module), cls)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Check a TOML value against a dataclass annotation; lists become tuples."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, where)
            except RecipeError:
                pass
        raise RecipeError(f"{where}: expected {' or '.join(_type_name(a) for a in args)}, got {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise RecipeError(f"{where}: must be one of {list(args)}, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, list):
            raise RecipeError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise RecipeError(f"{where}: expected a list of {len(args)} values, got {value!r}")
        return tuple(_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if origin is dict:
        if not isinstance(value, dict):
            raise RecipeError(f"{where}: expected a table, got {value!r}")
        return {str(k): _coerce(v, args[1], f"{where}.{k}") for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise RecipeError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise RecipeError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise RecipeError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise RecipeError(f"{where}: expected a string, got {value!r}")
        return value
    raise TypeError(f"{where}: unsupported annotation {tp!r}")


def build(cls: type, table: Any, where: str) -> Any:
    """Instantiate dataclass `cls` from a TOML table, naming `where` (file and table) in errors."""
    if not isinstance(table, dict):
        raise RecipeError(f"{where}: expected a table, got {table!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise RecipeError(f"{where}: unknown key '{unknown[0]}' (known keys: {', '.join(fields)})")
    kwargs = {}
    for name, f in fields.items():
        if name in table:
            kwargs[name] = _coerce(table[name], hints[name], f"{where} {name}")
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise RecipeError(f"{where}: missing required key '{name}'")
    try:
        return cls(**kwargs)
    except RecipeError:
        raise
    except ValueError as e:  # __post_init__ messages start with the key
        raise RecipeError(f"{where} {e}") from e


def parse_toml(text: str, file: str, known: set[str]) -> dict:
    """TOML text to a table; RecipeError naming `file` for bad TOML or an unknown top-level key."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise RecipeError(f"{file}: not valid TOML ({e})") from e
    unknown = sorted(set(data) - known)
    if unknown:
        raise RecipeError(f"{file}: unknown key '{unknown[0]}' (known: {', '.join(sorted(known))})")
    return data


def read_text(path: str | os.PathLike, what: str = "recipe") -> str:
    """A configuration file's text; RecipeError naming it when it cannot be read."""
    try:
        return Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise RecipeError(f"{path}: cannot read {what} ({e})") from e


def parse(text: str, file: str = "<recipe>") -> Recipe:
    """Parse and validate recipe TOML text; `file` names it in errors."""
    data = parse_toml(text, file, {"name", "seed", "sources", *SECTIONS})
    for key in ("name", "sources"):
        if key not in data:
            raise RecipeError(f"{file}: missing required key '{key}'")
    name = _coerce(data["name"], str, f"{file}: name")
    if not NAME_RE.match(name):
        raise RecipeError(f"{file}: name: letters, digits, '_' and '-' only, got {name!r}")
    seed = _coerce(data.get("seed", 0), int, f"{file}: seed")
    if not isinstance(data["sources"], list) or not data["sources"]:
        raise RecipeError(f"{file}: sources: need at least one [[sources]] table")
    sources = tuple(build(SourceSpec, s, f"{file}: [[sources]] #{i + 1}") for i, s in enumerate(data["sources"]))
    names = [s.name for s in sources]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise RecipeError(f"{file}: [[sources]] name: '{dup[0]}' used twice; give each source a distinct name")
    sections = {k: build(section_class(k), data.get(k, {}), f"{file}: [{k}]") for k in SECTIONS}
    return Recipe(
        name=name, seed=seed, sources=sources, sections=sections, file=file,
        sha256=hashlib.sha256(text.encode("utf-8")).hexdigest(), text=text,
    )


def load(path: str | os.PathLike) -> Recipe:
    """Read and validate a recipe file."""
    return parse(read_text(path), str(path))
