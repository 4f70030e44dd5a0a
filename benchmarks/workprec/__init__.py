"""The work-precision report behind ``python -m benchmarks.run``.

sizes.py    quick (CI) and full sizes of every section
measure.py  points, error measures, the exact-point check, interleaved timing, growth fits, floors
engine.py   the product path: a scene package opened by SceneEngine as the query server opens it
text.py, pose.py, gs.py, field.py, scaling.py, floor.py
            one section each: ``section`` (measure), ``markdown`` (table), ``reading``, ``plot``
plots.py    the shared work-precision diagram
report.py   stamps, CSV files, plots and REPORT.md
"""
