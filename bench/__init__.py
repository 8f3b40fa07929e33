"""Benchmarks (results and commands in bench/README.md).

Run each as a module from the repository root, e.g. ``.venv/bin/python -m bench.teacher``:
as modules of this package the scripts never shadow the packages they measure (a script
run by path puts its folder first on ``sys.path``, where ``bench/teacher.py`` would hide
the ``teacher`` package).
"""
