"""Batch reprocessing: many recordings through the pipeline (``vtcal batch``).

``run`` (:func:`run_batch`, fanned out over an executor), ``manifest`` (what a batch
runs), ``executor`` (where its tasks run: worker pools or Dask), ``outcome`` (one
recording's task and its small outcome), ``summary`` (the summary table and its
comparison), ``record`` (``batch.json``, the batch vouched for), ``cluster`` (a Dask
cluster started apart, checked before the first task).
"""
