"""What every stage shares: recipes, the stage runner, atomic I/O, the build folder's lock, seeding and errors.

Imports no other subpackage of meshsar_builder. The recipe's sections and the stages
are domain code, found through entry points (`meshsar.sections`, `meshsar.stages` in
pyproject.toml), never imported from here.
"""
