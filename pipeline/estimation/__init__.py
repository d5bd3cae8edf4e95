"""Estimation on eq. (1): whitening, identifiability, uncertainty, the solver's loss.

Eq. (1) itself (its layout, rows, :class:`~pipeline.measurement.pin.Problem` and
the linear pin/target solve) is :mod:`pipeline.measurement.pin`; this package
builds the estimation on it:

- :mod:`~pipeline.estimation.loss`: the robust loss that spares the constraint rows
- :mod:`~pipeline.estimation.whitening`: flange-frame whitening of the residuals
- :mod:`~pipeline.estimation.identifiability`: pivoted-QR column selection
- :mod:`~pipeline.estimation.uncertainty`: covariance and predicted pin error
- :mod:`~pipeline.estimation.correction_frame`, :mod:`~pipeline.estimation.region`,
  :mod:`~pipeline.estimation.distributions`

Used by identification (:mod:`pipeline.stages.identify.stage`), outlier rejection
(:mod:`pipeline.stages.outliers.stage`), cross-validation and pose planning
(:mod:`pipeline.plan.design`).
"""
