"""Benchmarks: the one part of lensfit above synth (it renders stacks with synth, then measures
and fits them with the lensfit core, and compares with the truth).

- ``suites``: suite files (``data_specs/bench/*.toml``) and the labels and ids of their cases;
- ``runs``: running a suite (render, noise, measure, fit; cached case files; process pool or Dask);
- ``report``: results.json, report.md and report.html with the plots;
- ``noise``: ``lensfit bench-fit`` (repeated noise draws on one rendered stack);
- ``measure``: ``lensfit bench-measure`` (the estimators on slanted edges and on a stack);
- ``lenses``: ``lensfit bench-lenses`` (thin- and thick-lens fits through real prescriptions).

The lensfit core never imports this package (``tests/test_layers.py``).
"""
