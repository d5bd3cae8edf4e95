"""The pipeline's stages, one subpackage per concept (``catalog.STAGES`` declares them).

- ``ingest/``: one streaming pass over a recording -> frames, detections, recording info
  (the stage, the pass, the joint states, its settings).
- ``image/``: the camera's image as recorded, before detection: its response curve (and
  its estimate from the images), the sensor's fixed gain pattern (flat field), binning
  of images too large for the detector.
- ``detect/``: the target's image ellipse, sub-pixel (the detector, its blob search,
  edge stage, ellipse geometry, the clipped-plate contour, its compiled kernel).
- ``touchup/``: from frames and detections to the touch-up table (segments, image
  Jacobian, targets, tilt, settling, swing, noise, the rows).
- ``trust/``: what the data and the fit can be trusted with: implausible inputs
  (plausibility), touch-ups identification must not trust (the outliers stage), a model
  that does not explain the data (adequacy).
- ``identify/``: from converged touch-ups to a calibrated robot (the stage, the fit's
  data, print shape, structure, tables, notes).
- ``crossval/``: which error model the run ships: held-out error of each (the crossval
  stage, its refits and predictions) and the choice by it (the choose stage).
- ``parallel_map``: the map over independent CPU-bound tasks the stages share.

A stage's entry module is ``stage.py`` in its package; the others are its parts.
"""
