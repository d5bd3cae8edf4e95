"""Estimation of eq. (1): the measurement equation, its Jacobian, whitening,
identifiability and uncertainty, in one place.

- :mod:`~pipeline.estimation.measurement`: the residuals and analytic Jacobian of
  eq. (1) with weights, known-distance rows and gauge (:class:`Problem`), its start
  point, the planning Jacobian, fitted target positions
- :mod:`~pipeline.estimation.whitening`: flange-frame whitening of the residuals
- :mod:`~pipeline.estimation.identifiability`: pivoted-QR column selection
- :mod:`~pipeline.estimation.uncertainty`: covariance and predicted pin error

Used by identification (:mod:`pipeline.stages.identify`), outlier rejection
(:mod:`pipeline.stages.outliers`), cross-validation and pose planning
(:mod:`pipeline.plan.design`).
"""
