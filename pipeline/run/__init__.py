"""The run's machinery: the declared stages and what walks them (``vtcal run``, ``vtcal identify``).

``catalog`` (the stage table, ``STAGES``; the run-folder files it writes are declared
below, in :mod:`pipeline.io.run_folder`; each stage's data-in/data-out function, its
node, is ``node.py`` in the stage's package), ``runner`` (walks the table, skips fresh stages, the only writer),
``orchestrator`` (``vtcal run``: the ledger's shortcut, ingest, the later stages'
options, ``run.json``), ``code_key`` (the digest of a stage's code, part of its cache
key), ``ledger`` (the run ledger in ``run.json``), ``withdraw`` (nothing partial left
by a refused run), ``threads`` (one BLAS thread per process, set by the CLI
before numpy loads).

Above the stages and the report, which it runs: nothing below imports it (the report
is handed its code digest by the orchestrator). Importing the package imports none of
its modules (the ledger's shortcut loads no stage).
"""
