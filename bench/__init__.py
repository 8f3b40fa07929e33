"""Benchmarks: each script writes its record ``bench/results/<name>.json`` (:mod:`bench.record`),
and :mod:`bench.tables` makes bench/README.md's tables from those records.

Run each as a module from the repository root, e.g. ``.venv/bin/python -m bench.teacher``.
"""
