"""The identify stage's options, the robot a fit is of, its result per error model, and its failure."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

from pipeline.errors import BadInput, CalibrationFailed
from pipeline.kinematics.chain import Chain, load_chain
from pipeline.kinematics.se3 import F64
from pipeline.models import make_model
from pipeline.models.base import ErrorModel
from pipeline.stages.identify.print_shape import ShapeFit

DEFAULT_MODEL = "full"


#: ``model="auto"`` tries these in order and keeps the first the touch-ups support
AUTO_ORDER = ("full", "offsets")


class TooFewTouchups(CalibrationFailed):
    """The touch-ups leave no redundancy for the model's identifiable parameters."""


@dataclass
class IdentifyConfig:
    """Identification settings.

    Attributes
    ----------
    model : error model name (``full``, ``mdh``, ``poe``, ``offsets``, ``elastic``), ``all`` (fit each), or
        ``auto`` (``full`` if the touch-ups suffice, else ``offsets``; the summary says which)
    distances : known distances ``(label A, label B, metres)`` between targets
    robust_loss : ``scipy.optimize.least_squares`` loss (``linear``, ``soft_l1``, ``huber``, ``cauchy``, ...)
    f_scale : soft threshold of a robust loss, metres of pin residual
    distance_weight : weight of a known-distance residual relative to a touch-up row
    rank_tol : relative pivot threshold below which a parameter is structurally unidentifiable
    data_tol : relative pivot threshold below which these touch-ups do not excite a parameter
    noise_model : ``flange`` (estimate the pin error's 3x3 covariance in the flange frame from
        the residuals and refit whitened: a touch-up is far less precise along the view than
        across it) or ``isotropic``
    target_components : ``report`` (each target's variance factor and Bartlett's test of
        their equality reported in the summary, the fit unchanged), ``auto`` (the targets
        weighed by their own scatter when the test rejects at 1 %:
        :mod:`pipeline.stages.identify.components`) or ``off``
    max_nfev : iteration budget of the solver
    n_workspace : poses over which the predicted error is evaluated
    seed : seed of those poses
    target_shape : the targets' print shape (:mod:`pipeline.stages.identify.print_shape`): ``auto`` fits
        each target's size (relative to the first) and out-of-roundness when the table has
        the shape columns and every target ``shape_min_touchups`` touch-ups, and keeps them
        when an F-test at ``shape_alpha`` finds them significant; ``fit`` keeps them whenever
        they can be fitted; ``none`` never fits them
    shape_alpha, shape_min_touchups : see ``target_shape``. ``shape_alpha = 1e-4``: a
        run fits up to four models with two tests each, so about ``1e-3`` per run
        (Bonferroni). At ``1e-3`` a linear-image UR5e-like cell with perfect prints was
        fitted at p = 7.6e-4 and lost 5 % of shape accuracy; 20 um out-of-round prints
        give p ~ 1e-34.
    target_diameter_m : printed diameter, to state print errors in micrometres (else relative)
    implied_target_diameter_m : the diameter the touch-up stage's image Jacobian implies
        (:func:`pipeline.measurement.image.diameter_from_jacobian`), checked against
        ``target_diameter_m`` by the guardrails; None for a table without images
    pin_offset_cov_m2 : (3 x 3 nested list, m^2, flange frame) the covariance of the
        touch-ups' pose component (:func:`pipeline.stages.touchups.noise.pose_noise`): its
        mean over the recording is a constant pin offset no residual sees, added to the
        pin's covariance before the predicted errors (P1 of
        :func:`pipeline.estimation.uncertainty.with_pin_offset`);
        None (single captures, a table without images): nothing added
    accept_implausible : identify even where :mod:`pipeline.guardrails.plausibility` finds an
        input the nominal robot contradicts (joint values outside the URDF's limits, a
        known distance off by more than the nominal robot's own error); the lines are
        then kept in the summary as ``implausible``
    check_plausibility : run those guardrails at all; False for refits on a subset of
        touch-ups whose full table passed them (cross-validation), ``implausible`` then []
    prediction_only : a refit whose only use is to predict (cross-validation's folds):
        the fit is the same, but no covariance, parameter and residual tables or URDF
        are made; ``targets`` holds the fitted positions and ``summary`` only
        ``rms_mm``, ``sigma_mm`` and ``n_identified``
    strict_distances : a known distance naming a target absent from the table is bad input
        (``vtcal identify``); False drops it with a note (``vtcal run``: the recording's
        metadata names every target of the cell, a truncated run may not have reached them all)
    correction_frame : the frame the residual corrections ``d_i`` are taken in. ``calibrated``:
        a first fit (the first of ``AUTO_ORDER`` that can be fitted, prediction only), then
        ``d_i -> M_eff d_i`` with ``M_eff`` the pose-averaged map from nominal to calibrated
        flange translations (:mod:`pipeline.estimation.correction_frame`: the touch-up stage's
        image Jacobian was measured with nominal translations), then the fit;
        ``nominal``: the corrections as the table has them
    correction_map : a given ``M_eff`` (3 x 3 nested list) instead of the first fit's:
        cross-validation's refits take the full fit's (:func:`pipeline.stages.crossval.stage.refit_config`)
    workers : processes the error models of ``model="all"`` are fitted in; 1 in this
        process, 0 picks 2 when the machine has a core to spare
        (:func:`pipeline.stages.parallel_map.parallel_map`). The results are the same.
    """

    model: str = "auto"
    distances: list[tuple[int | str, int | str, float]] = field(default_factory=list)
    robust_loss: str = "linear"
    f_scale: float = 1e-4
    distance_weight: float = 100.0
    rank_tol: float = 1e-8
    data_tol: float = 1e-6
    noise_model: str = "flange"
    reweight_passes: int = 1
    target_components: str = "report"
    max_nfev: int = 200
    n_workspace: int = 200
    seed: int = 0
    strict_distances: bool = True
    target_shape: str = "auto"
    shape_alpha: float = 1e-4
    shape_min_touchups: int = 6
    target_diameter_m: float | None = None
    implied_target_diameter_m: float | None = None
    pin_offset_cov_m2: list[list[float]] | None = None
    accept_implausible: bool = False
    check_plausibility: bool = True
    prediction_only: bool = False
    correction_frame: str = "calibrated"
    correction_map: list[list[float]] | None = None
    workers: int = 0


@dataclass
class Robot:
    """The nominal robot fits are of: its URDF, its chain and its error models, each made once.

    A model holds the nominal chain and no fit state (its methods take ``x``), so one
    object serves every fit of that model: cross-validation's refits share them.

    Attributes
    ----------
    urdf : nominal URDF XML
    chain : base link -> flange (or tool) link of ``urdf``
    """

    urdf: str
    chain: Chain
    _models: dict[str, ErrorModel] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def load(cls, urdf: str, base_link: str, flange_link: str) -> Robot:
        """The robot of ``urdf`` from ``base_link`` to ``flange_link``."""
        return cls(urdf, load_chain(urdf, base_link, flange_link))

    def model(self, name: str) -> ErrorModel:
        """The error model ``name`` of :attr:`chain` (:func:`pipeline.models.make_model`),
        made on first use; BadInput for an unknown name."""
        if name not in self._models:
            try:
                self._models[name] = make_model(name, self.chain)
            except KeyError as exc:
                raise BadInput(f"--model {name!r}: {exc.args[0]}") from exc
        return self._models[name]


class PrintRows(NamedTuple):
    """Rows' print-shape geometry for :meth:`IdentifyResult.predict`: levers ``g`` and
    long-axis directions ``l`` (N, 3) each, flange frame, target ids (N,) and the image
    anisotropy (N,) of (S3) (None: (S2))."""

    g: F64
    l: F64
    target_id: np.ndarray
    v_mag: F64 | None = None


@dataclass
class IdentifyResult:
    """Everything identification produces for one error model.

    Attributes
    ----------
    model : error model name
    parameters, residuals, targets : artefact tables (``schemas/NAME.json``)
    calibrated_urdf : nominal URDF with the corrections in its joint origins and the virtual pin
    summary : JSON-able figures (see :func:`identify`)
    chain : calibrated chain, base link to flange link
    p_flange_pin : (3,) identified virtual pin, flange frame
    x : (P,) model parameters (held ones 0)
    error_model : the fitted model: ``error_model.pin_and_jacobian(x, q, pin)`` predicts
        the pin exactly, also where ``chain`` (the URDF's rigid kinematics) cannot
        (a model with ``urdf_exact = False``)
    correction_map : (3, 3) ``M_eff`` the fit applied to the table's corrections
        (``IdentifyConfig.correction_frame``; the identity for ``nominal``)
    target_xyz : ``{target_id: (3,) fitted position, m}``: the positions of ``targets``,
        also where a prediction-only fit makes no targets table
    print_shape : the fitted print shape (:class:`pipeline.stages.identify.print_shape.ShapeFit`),
        None when the fit kept perfect circles of one size
    covariance : (Z, Z) the fit's covariance ``sigma^2 (J^T J)^-1`` of its estimated
        unknowns (:func:`pipeline.estimation.uncertainty.covariance`), None where none was
        made ; covariance_names : (Z,) their names (:func:`pipeline.stages.identify.tables.covariance_names`)
    """

    model: str
    parameters: pd.DataFrame
    residuals: pd.DataFrame
    targets: pd.DataFrame
    calibrated_urdf: str
    summary: dict[str, Any]
    chain: Chain
    p_flange_pin: F64
    x: F64 = field(repr=False, default_factory=lambda: np.zeros(0))
    error_model: ErrorModel | None = field(repr=False, default=None)
    correction_map: F64 = field(repr=False, default_factory=lambda: np.eye(3))
    target_xyz: dict[int, F64] = field(repr=False, default_factory=dict)
    print_shape: ShapeFit | None = field(repr=False, default=None)
    covariance: F64 | None = field(repr=False, default=None)
    covariance_names: list[str] = field(repr=False, default_factory=list)

    def predict(self, q: F64, d: F64, shape: PrintRows | None = None) -> F64:
        """Pin positions of the fitted model, (N, 3):

            p_i = T_base_flange(q_i; x) (p_pin + M_eff d_i + eps_i g_i)

        ``d`` as the table has it; ``M_eff`` is :attr:`correction_map`. The print term
        ``eps_i g_i`` ((S1)-(S2) of :mod:`pipeline.stages.identify.print_shape`) is added when the
        fit kept a print shape and ``shape`` gives the rows' levers, long axes and
        targets: the fit corrected its own touch-ups so, and a touch-up it has not seen
        (held out) stops off its target by the same print error.
        """
        pts = self.p_flange_pin[None, :] + np.asarray(d, dtype=float) @ self.correction_map.T
        if self.error_model is not None:
            p, R, _ = self.error_model.pin_and_jacobian(self.x, q, pts, jac=False)
        else:
            from pipeline.kinematics.chain import fk

            T = fk(self.chain, q)
            R = T[:, :3, :3]
            p = np.einsum("nij,nj->ni", R, pts) + T[:, :3, 3]
        if self.print_shape is not None and shape is not None:
            lever = self.print_shape.lever_terms(R, shape.g, shape.l, shape.target_id, shape.v_mag)
            p = p + np.einsum("nij,nj->ni", R, lever)
        return np.asarray(p)
