"""``khepri study``: a grid of simulation runs (the paper's, or one from a YAML file), executed on a local
process pool or a Dask cluster, resumable, aggregated into summary.csv, report.md and figures next to the
paper's numbers. See docs/study.md.

Modules: ``study_file`` (reading a study file), ``grid`` (what to run), ``worker`` (one run), ``executors``
(where), ``driver`` (resume, progress), ``aggregate`` (statistics, summary.csv), ``report`` (report.md),
``figures`` (PNG), ``paper_reference`` (the paper's data in ``data/``).
"""
