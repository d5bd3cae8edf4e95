"""The pipeline's stages: one subpackage per stage of ``catalog.STAGES``, named as the stage
(``ingest``, ``touchups``, ``outliers``, ``identify``, ``crossval``, ``choose``; the report's
code is :mod:`pipeline.report`), and ingest's sub-concepts beside them (``image``,
``detect``, ``response``: the camera's image, the detector and the response curve ingest
applies to every frame).

- ``ingest/``: one streaming pass over a recording -> frames, detections, recording info
  (the stage, the pass, the joint states, its settings).
- ``image/``: the camera's image as recorded, before detection: its response curve (and
  its estimate from the images), the sensor's fixed gain pattern (flat field), binning
  of images too large for the detector.
- ``detect/``: the target's image ellipse, sub-pixel (the detector, its blob search,
  edge stage, ellipse geometry, the clipped-plate contour, its compiled kernel).
- ``touchups/``: from frames and detections to the touch-up table (segments, image
  Jacobian, targets, tilt, settling, swing, noise, the rows).
- ``outliers/``: what the data and the fit can be trusted with: touch-ups identification
  must not trust (the outliers stage), a model that does not explain the data
  (adequacy; the choose stage records it). Implausible inputs are
  :mod:`pipeline.guardrails.plausibility`, below the stages.
- ``identify/``: from converged touch-ups to a calibrated robot (the stage, the fit's
  data, print shape, structure, tables, notes).
- ``crossval/``: the held-out error of each error model (the crossval stage, its refits
  and predictions).
- ``choose/``: which error model the run ships, by that error (the choose stage).
- ``parallel_map``: the map over independent CPU-bound tasks the stages share.

A stage's entry module is ``stage.py`` in its package; the others are its parts.

A stage's ``node.py`` holds its node, called by the runner as declared in
:data:`pipeline.run.catalog.STAGES`: the artefacts the stage reads (``data``), its
options and the run's context (:class:`pipeline.run.runner.Context`) in,
``{artefact key: value}`` out for the runner to write; a node writes no file. The
stage's computation is imported inside the node, so importing a node module stays
cheap (the catalog imports them all) and a function replaced at run time is the one
that runs (and the one the stage code key hashes, :mod:`pipeline.run.code_key`).
The report's node (:mod:`pipeline.report.node`) keeps the same contract.
"""
