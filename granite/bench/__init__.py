"""``granite bench``: studies of scenarios x terrain seeds x VO variants, executed as Dask tasks
(see ``docs/bench.md``): :mod:`~granite.bench.study` (the study file),
:mod:`~granite.bench.tasks` (render, finalize, VO run, evaluation), :mod:`~granite.bench.execute`
(planning and running them, resumable) and :mod:`~granite.bench.report` (results.csv, report.md,
plots)."""
