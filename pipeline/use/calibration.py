"""A run's calibration as a robot model to use: where the tool goes, which joints put it there.

:func:`pipeline.use.load` returns a :class:`Calibration` built from a run's
``calibration.json`` (:mod:`pipeline.use.record`): the error model the run
predicts with (compliance included where the run chose ``elastic``), its
parameters, pin, covariance and covered region.

Forward (paper eq. 1, the pin a point of the flange frame)::

    T_base_flange(q) = FK(x; q),        p_base_pin = R(q) p_flange_pin + t(q)     (U1)

with ``FK`` the error model's map (:meth:`pipeline.models.base.ErrorModel.pin_and_jacobian`).
Its uncertainty is the parameter covariance ``C`` carried through the model's
Jacobian ``J_e = [dp/dx_kept, R]`` (the estimated kinematic columns, then the pin)::

    Cov(p_base_pin) = J_e C J_e^T,      sigma_pin = sqrt(trace Cov)               (U2)

conditional on the base frame the calibration defines (touch-ups never tell
the base frame against the targets; :mod:`pipeline.estimation.uncertainty` has
the registered kinds). The inverse is :mod:`pipeline.use.inverse`.

Shapes: ``q`` (N, n) joint vectors in :attr:`Calibration.joint_names` order
(a single (n,) vector is taken as N = 1), SI units throughout.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from pipeline.errors import BadInput
from pipeline.kinematics.se3 import F64
from pipeline.use.record import FORMAT


@dataclass(frozen=True)
class Prediction:
    """Where the calibrated robot puts its flange and virtual pin, per joint vector.

    Attributes
    ----------
    T_base_flange : (N, 4, 4) flange poses in the base frame
    p_base_pin : (N, 3) virtual-pin positions in the base frame, m
    cov_pin : (N, 3, 3) covariance of ``p_base_pin`` from the parameters' (U2), m^2
    sigma_pin_m : (N,) ``sqrt(trace(cov_pin))``, m
    inside : (N,) bool: every joint inside the range the touch-ups covered
    outside : (N,) names of the joints outside it, comma separated ('' inside)
    """

    T_base_flange: F64
    p_base_pin: F64
    cov_pin: F64
    sigma_pin_m: F64
    inside: np.ndarray
    outside: list[str]


class Calibration:
    """A calibrated robot: :meth:`forward`, :meth:`inverse`, :meth:`covers` (module docstring).

    Attributes
    ----------
    model : error model name (``elastic`` carries joint compliance)
    joint_names : actuated joints, chain order (the columns ``q`` is read in)
    p_flange_pin : (3,) virtual pin in the flange frame, m
    lower, upper : (n,) the covered joint ranges, rad (``-inf, inf`` where unknown)
    limit_lower, limit_upper : (n,) the URDF's joint limits, rad
    record : the ``calibration.json`` dict it was built from
    """

    def __init__(self, record: dict[str, Any]) -> None:
        from pipeline.kinematics.chain import load_chain
        from pipeline.models import get_model

        if record.get("format") != FORMAT:
            raise BadInput(f"calibration record format {record.get('format')!r}, not {FORMAT!r}")
        self.record = record
        robot = record["robot"]
        self.chain = load_chain(robot["urdf"], robot["base_link"], robot["flange_link"])
        self.model = str(record["model"])
        self.error_model = get_model(self.model)(self.chain)
        names = list(self.error_model.param_names)
        if names != list(record["parameters"]["names"]):
            raise BadInput(
                f"calibration record: model {self.model}'s parameters "
                f"{record['parameters']['names'][:3]}... do not match this vtcal's {names[:3]}..."
            )
        self.x = np.asarray(record["parameters"]["values"], dtype=float)
        self.p_flange_pin = np.asarray(record["p_flange_pin"], dtype=float)
        self.joint_names = list(self.chain.joint_names)
        cov = record.get("covariance") or {}
        cnames = list(cov.get("names") or [])
        self._cov = np.asarray(cov.get("matrix") or np.zeros((0, 0)), dtype=float)
        self._kin_cols = np.array([names.index(n) for n in cnames if not n.startswith("pin.")])
        self._n_pin = sum(n.startswith("pin.") for n in cnames)
        ranges = (record.get("region") or {}).get("joint_ranges_rad") or {}
        self.lower = np.array([ranges.get(j, [-np.inf, np.inf])[0] for j in self.joint_names])
        self.upper = np.array([ranges.get(j, [-np.inf, np.inf])[1] for j in self.joint_names])
        self.limit_lower = np.asarray(self.chain.lower, dtype=float)
        self.limit_upper = np.asarray(self.chain.upper, dtype=float)
        self._payload_models: dict[float, Any] = {}  # one model instance per payload

    @property
    def has_payload(self) -> bool:
        """Whether the model's predictions depend on a payload (an elastic model)."""
        return hasattr(self.error_model, "set_payload")

    def _with_payload(self, payload_kg: float | None) -> Any:
        """The error model with ``payload_kg`` at the flange (None: as in training).

        A payload gets a model instance of its own, made once (the inverse evaluates
        the model many times per row): the shared one keeps the training payload.
        """
        if payload_kg is None or not self.has_payload:
            return self.error_model
        kg = float(payload_kg)
        if kg not in self._payload_models:
            from pipeline.models import get_model

            em: Any = get_model(self.model)(self.chain)
            em.set_payload(kg)
            self._payload_models[kg] = em
        return self._payload_models[kg]

    def pin_and_rotation(
        self, q: ArrayLike, payload_kg: float | None = None, point: ArrayLike | None = None
    ) -> tuple[F64, F64]:
        """``(p_base, R_base_flange)`` of a flange-frame point (default: the pin), (N, 3), (N, 3, 3)."""
        q2 = self.as_joints(q)
        p_f = self.p_flange_pin if point is None else np.asarray(point, dtype=float)
        em = self._with_payload(payload_kg)
        p, R, _ = em.pin_and_jacobian(self.x, q2, p_f, jac=False)
        return p, R

    def as_joints(self, q: ArrayLike) -> F64:
        """``q`` as an (N, n) float array; refuses a wrong width or a non-finite value."""
        q2 = np.atleast_2d(np.asarray(q, dtype=float))
        if q2.ndim != 2 or q2.shape[1] != len(self.joint_names):
            raise BadInput(
                f"joint vectors of width {q2.shape[-1]}, not {len(self.joint_names)} "
                f"({', '.join(self.joint_names)})"
            )
        bad = ~np.all(np.isfinite(q2), axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise BadInput(f"joint vector {i} holds a value that is not a finite number: {q2[i]}")
        return q2

    def covers(self, q: ArrayLike) -> tuple[np.ndarray, list[str]]:
        """Per joint vector: inside the covered ranges (bool, (N,)) and the joints outside."""
        q2 = self.as_joints(q)
        out = (q2 < self.lower) | (q2 > self.upper)
        names = [
            ",".join(j for j, o in zip(self.joint_names, row, strict=True) if o) for row in out
        ]
        inside = np.asarray(~out.any(axis=1), dtype=bool)
        return inside, names

    def forward(self, q: ArrayLike, payload_kg: float | None = None) -> Prediction:
        """(U1) and (U2) at the joint vectors ``q`` (N, n); ``payload_kg`` at the flange.

        ``payload_kg`` changes an elastic model's gravity torque (None: the payload
        the calibration was measured with); a rigid model ignores it.
        """
        q2 = self.as_joints(q)
        em = self._with_payload(payload_kg)
        p, R, J = em.pin_and_jacobian(self.x, q2, self.p_flange_pin, jac=True)
        T = np.tile(np.eye(4), (len(q2), 1, 1))
        T[:, :3, :3] = R
        T[:, :3, 3] = p - R @ self.p_flange_pin  # the flange origin: (U1) solved for t(q)
        if self._cov.size and J is not None:
            parts = [J[:, :, self._kin_cols]] if self._kin_cols.size else []
            if self._n_pin:
                parts.append(R)
            Je = np.concatenate(parts, axis=2)
            cov = np.einsum("nip,pq,njq->nij", Je, self._cov, Je)
        else:
            cov = np.full((len(q2), 3, 3), np.nan)
        inside, outside = self.covers(q2)
        sigma = np.sqrt(np.clip(np.trace(cov, axis1=1, axis2=2), 0, None))
        return Prediction(T, p, cov, sigma, inside, outside)

    def inverse(
        self,
        T_base_target: ArrayLike,
        q0: ArrayLike,
        point: str = "flange",
        payload_kg: float | None = None,
    ) -> Any:
        """Joint vectors that put the flange (or the pin) on targets: :func:`pipeline.use.inverse.solve`.

        ``T_base_target`` (N, 4, 4) target poses (``point="flange"``: pose of the
        flange; ``"pin"``: the position only, its translation), ``q0`` (N, n) or
        (n,) starting joints (the nominal program's, usually).
        """
        from pipeline.use.inverse import solve

        return solve(self, T_base_target, q0, point=point, payload_kg=payload_kg)


def load(run_dir: str | Path) -> Calibration:
    """The calibration a run folder ships (its ``calibration.json``).

    Raises
    ------
    BadInput
        The folder has no ``calibration.json`` (a run from an older vtcal: run it
        again), or the file is not a calibration record.
    """
    from pipeline.io.run_folder import RUN_FILES

    path = Path(run_dir) / RUN_FILES["calibration"]
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise BadInput(
            f"{path}: no calibration record in this run folder (made by vtcal run / identify "
            "from this version on: run it again)"
        ) from exc
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BadInput(f"{path}: not a readable calibration record: {exc}") from exc
    try:
        return Calibration(record)
    except BadInput as exc:
        raise BadInput(f"{path}: {exc}") from exc
    except (KeyError, TypeError, ValueError) as exc:
        raise BadInput(f"{path}: calibration record incomplete: {exc!r}") from exc
