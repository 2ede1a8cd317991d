"""Many recordings at once: ``lego_loam_py batch`` and its Python API, runs of the offline pipeline on Dask.

    from lego_loam_py.batch import parameter_grid, run_batch
    result = run_batch(['bags/*'], parameter_grid(['feature_association.edge_threshold:=0.1,0.2']), 'out/sweep')
    result.table()   # a pandas DataFrame, one row per run

Modules: :mod:`~lego_loam_py.batch.plan` (what runs, and each run's identity), :mod:`~lego_loam_py.batch.execute`
(one run, atomically), :mod:`~lego_loam_py.batch.driver` (Dask, resume, retries), :mod:`~lego_loam_py.batch.report`
(report.md, report.csv, plots), :mod:`~lego_loam_py.batch.cli` (the command).
"""

from __future__ import annotations

from lego_loam_py.batch.driver import BatchResult, local_cluster, run_batch
from lego_loam_py.batch.plan import ParameterSet, RunSpec, parameter_grid
from lego_loam_py.batch.report import collect_records, write_report

__all__ = [
    'run_batch',
    'BatchResult',
    'local_cluster',
    'ParameterSet',
    'RunSpec',
    'parameter_grid',
    'collect_records',
    'write_report',
]
