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
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from meshsar_builder.pipeline.errors import RecipeError

# Recipe table -> "module:Class" of the parameter dataclass that defines its keys, and the class
# of a [[sources]] entry. They are domain code, registered as entry points in pyproject.toml
# (group meshsar.sections), so the pipeline imports no domain; each is imported only when a
# recipe is parsed (the splits and verify commands should not pay for trimesh or torch).
_REGISTERED = {ep.name: ep.value for ep in entry_points(group="meshsar.sections")}
SOURCES_ENTRY = "sources"
SECTIONS: dict[str, str] = {name: value for name, value in sorted(_REGISTERED.items()) if name != SOURCES_ENTRY}

NAME_RE = re.compile(r"^[A-Za-z0-9_-]+$")


@dataclass(frozen=True)
class Recipe:
    name: str
    seed: int
    sources: tuple[Any, ...]  # the registered [[sources]] class, e.g. dataset.sources.SourceSpec
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
    """The dataclass registered for recipe table `name` (or SOURCES_ENTRY for [[sources]])."""
    module, cls = _REGISTERED[name].split(":")
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
    if seed < 0:
        raise RecipeError(f"{file}: seed: must be >= 0 (numpy's seed sequences take non-negative integers), got {seed}")
    if not isinstance(data["sources"], list) or not data["sources"]:
        raise RecipeError(f"{file}: sources: need at least one [[sources]] table")
    sources = tuple(build(section_class(SOURCES_ENTRY), s, f"{file}: [[sources]] #{i + 1}") for i, s in enumerate(data["sources"]))
    names = [s.name for s in sources]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise RecipeError(f"{file}: [[sources]] name: '{dup[0]}' used twice; give each source a distinct name")
    sections = {k: build(section_class(k), data.get(k, {}), f"{file}: [{k}]") for k in SECTIONS}
    return Recipe(
        name=name, seed=seed, sources=sources, sections=sections, file=file,
        sha256=hashlib.sha256(text.encode("utf-8")).hexdigest(), text=text,
    )


def override(recipe: Recipe, table: str, key: str, value: Any, where: str) -> Recipe:
    """The recipe with [table] key set to value, checked like the file's own keys; RecipeError naming `where`.

    For command-line settings that belong to a table (meshsar build --device sets [radar]
    device). The recipe's text, digest and file stay those of the file: the override
    reaches the stages through recipe.<table> in the build's Context, as the file's keys do.
    """
    section = recipe.sections[table]
    hints = typing.get_type_hints(type(section))
    if key not in {f.name for f in dataclasses.fields(section) if f.init}:
        raise RecipeError(f"{where}: [{table}] has no key '{key}'")
    try:
        changed = dataclasses.replace(section, **{key: _coerce(value, hints[key], f"{where}")})
    except RecipeError:
        raise
    except ValueError as e:  # __post_init__ messages start with the key
        raise RecipeError(f"{where}: {e}") from e
    return dataclasses.replace(recipe, sections={**recipe.sections, table: changed})


def load(path: str | os.PathLike) -> Recipe:
    """Read and validate a recipe file."""
    return parse(read_text(path), str(path))
