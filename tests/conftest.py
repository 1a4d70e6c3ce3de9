import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("MPLBACKEND", "Agg")

# `--doctest-modules` (pyproject) is for src/: this file is not a module of examples, and
# importing it as one would clash with src/conftest.py under the same name
collect_ignore = ["conftest.py"]
