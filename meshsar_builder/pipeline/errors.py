"""Errors that name what went wrong; a stage records them per item in failures.json."""


class MeshsarError(Exception):
    """Base of the project's own errors."""


class RecipeError(MeshsarError, ValueError):
    """A recipe is malformed: the message names the file and the key."""


class InputError(MeshsarError, ValueError):
    """An input file is unreadable or unusable: the message names the file and the problem."""


class MeshError(MeshsarError, ValueError):
    """A mesh fails a geometric requirement (watertight, genus 0, no self-intersections, fit)."""
