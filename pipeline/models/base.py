"""The error-model interface, its registry and the twist algebra every model shares.

An error model parameterises the kinematics of a serial chain (base link to
flange link) by a vector ``x`` of small corrections to the nominal URDF
(``x = 0`` is the nominal robot). It answers three questions:

* where the flange-frame points ``p_flange`` land in the base frame at joint
  vectors ``q`` and how they move with ``x`` (:meth:`ErrorModel.pin_and_jacobian`);
* which URDF joint origins reproduce the corrected kinematics
  (:meth:`ErrorModel.origins`), so a calibrated URDF is exact;
* the names, joints and units of its parameters.

Analytic Jacobians come from one identity. If the product of transforms that
gives ``T_base_flange`` contains a factor perturbed on its right by a local
twist ``xi = (v, w)`` (``F -> F exp([xi])``) at a frame whose base pose is
``T_base_F = (R, o)``, a point ``p`` (base frame) carried by everything after
it moves by

    dp = R v + (R w) x (p - o)                                   (1)

(the adjoint map of the twist to the base frame, applied to the point; Murray,
Li & Sastry 1994, ch. 2). Every parameter of every model is such a twist (or a
sum of them), so each model only records the frames and twists of its factors.

A new model is one new module in :mod:`pipeline.models` that subclasses
:class:`ErrorModel` and decorates it with :func:`register`; the package imports
every such module and answers ``get_model`` / ``model_names``.
"""

from __future__ import annotations

import functools
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import F64, skew

REGISTRY: dict[str, type[ErrorModel]] = {}
_I3 = np.eye(3)
_I4 = np.eye(4)


def register(cls: type[ErrorModel]) -> type[ErrorModel]:
    """Class decorator: make an error model available by its ``name``."""
    REGISTRY[cls.name] = cls
    return cls


@dataclass(frozen=True)
class ChainLayout:
    """The nominal chain cut at its actuated joints.

    ``T_base_flange(q) = prod_k [pre_k @ origin_k @ M_k(q_k)] @ tail`` with
    ``pre_k`` the product of the fixed joints between actuated joint ``k-1``
    and ``k`` and ``tail`` the fixed joints after the last one.

    Attributes
    ----------
    names : joint names, (n,)
    pre : (n, 4, 4)
    origin : (n, 4, 4) nominal ``T_parent_joint`` of each actuated joint
    axis : (n, 3) unit axes in the joint frames
    prismatic : (n,) bool
    tail : (4, 4)
    """

    names: tuple[str, ...]
    pre: F64
    origin: F64
    axis: F64
    prismatic: np.ndarray
    tail: F64

    @classmethod
    def from_chain(cls, chain: Chain) -> ChainLayout:
        pre, origin, axis, pris, names = [], [], [], [], []
        acc = np.eye(4)
        for j in chain.joints:
            if j.actuated:
                pre.append(acc)
                origin.append(np.asarray(j.T_parent_joint, dtype=float))
                axis.append(np.asarray(j.axis, dtype=float))
                pris.append(j.type == "prismatic")
                names.append(j.name)
                acc = np.eye(4)
            else:
                acc = acc @ j.T_parent_joint
        return cls(
            names=tuple(names),
            pre=np.array(pre).reshape(-1, 4, 4),
            origin=np.array(origin).reshape(-1, 4, 4),
            axis=np.array(axis).reshape(-1, 3),
            prismatic=np.array(pris, dtype=bool),
            tail=acc,
        )

    @property
    def n(self) -> int:
        return len(self.names)


class ErrorModel(ABC):
    """A parameterisation of a chain's kinematic errors (see module docstring).

    Subclasses set ``name`` and ``description`` and fill ``param_names``,
    ``param_joints`` and ``param_units`` (``"m"``, ``"rad"``, ...) in ``__init__``.
    Everything else a model may provide is declared here with its default:

    * ``param_priority`` (P,): tie-break among exactly dependent columns in the
      identifiability QR (a larger value is kept); default all 1;
    * ``param_nominal`` (P,): the nominal value of the quantity each parameter
      corrects (the DH table for ``mdh``), written to parameters.parquet's
      ``nominal``; default all 0 (pure corrections);
    * ``urdf_exact``: :meth:`origins` reproduce the model exactly;
    * :meth:`column_scale`: the identification's column scaling.
    """

    name: str = ""
    description: str = ""
    #: :meth:`origins` reproduce the model exactly (False: the model has
    #: configuration-dependent terms a URDF cannot carry; never shipped as calibrated.urdf)
    urdf_exact: bool = True

    @classmethod
    def applies(cls, chain: Chain) -> bool:
        """Whether the model can be built on ``chain`` (False: ``--model all`` leaves it out;
        e.g. a model on the URDF's inertials where the URDF has none)."""
        return True

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Wrap a subclass's :meth:`pin_and_jacobian` with :meth:`check_inputs`.

        The check runs when the method is called on an instance of the class that
        defines it (a subclass calling ``super().pin_and_jacobian`` with its own
        slice of ``x`` is not checked against its own parameter count).
        """
        super().__init_subclass__(**kwargs)
        impl = cls.__dict__.get("pin_and_jacobian")
        if impl is None or getattr(impl, "__isabstractmethod__", False):
            return

        @functools.wraps(impl)
        def checked(
            self: ErrorModel, x: ArrayLike, q: ArrayLike, p_flange: ArrayLike, *, jac: bool = True
        ) -> tuple[F64, F64, F64 | None]:
            if type(self).pin_and_jacobian is checked:
                self.check_inputs(x, q, p_flange)
            return impl(self, x, q, p_flange, jac=jac)  # type: ignore[no-any-return]

        cls.pin_and_jacobian = checked  # type: ignore[method-assign]

    def __init__(self, chain: Chain) -> None:
        self.nominal = chain
        self.layout = ChainLayout.from_chain(chain)
        self.param_names: list[str] = []
        self.param_joints: list[str] = []
        self.param_units: list[str] = []
        self._priority: F64 | None = None
        self._nominal: F64 | None = None

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def param_priority(self) -> F64:
        """(P,) pivoting tie-break weights (see the class docstring); default ones."""
        return np.ones(self.n_params) if self._priority is None else self._priority

    @param_priority.setter
    def param_priority(self, value: ArrayLike) -> None:
        self._priority = np.asarray(value, dtype=float)

    @property
    def param_nominal(self) -> F64:
        """(P,) nominal value of what each parameter corrects; default zeros."""
        return np.zeros(self.n_params) if self._nominal is None else self._nominal

    @param_nominal.setter
    def param_nominal(self, value: ArrayLike) -> None:
        self._nominal = np.asarray(value, dtype=float)

    def check_contract(self) -> None:
        """Raise ``ValueError`` if the declared per-parameter lists disagree in length."""
        P = self.n_params
        sizes = {
            "param_joints": len(self.param_joints),
            "param_units": len(self.param_units),
            "param_priority": len(self.param_priority),
            "param_nominal": len(self.param_nominal),
        }
        bad = {k: v for k, v in sizes.items() if v != P}
        if bad:
            raise ValueError(f"error model {self.name!r}: {P} param_names but {bad}")

    def check_inputs(self, x: ArrayLike, q: ArrayLike, p_flange: ArrayLike) -> None:
        """Raise ``ValueError`` naming the shape when :meth:`pin_and_jacobian`'s inputs are off.

        ``x`` must be (P,), ``q`` (N, n) or (n,), ``p_flange`` (3,) or (N, 3).
        """
        xs, qs, ps = np.shape(x), np.shape(q), np.shape(p_flange)
        n = self.layout.n
        if xs != (self.n_params,):
            raise ValueError(
                f"error model {self.name!r}: x has shape {xs}, expected ({self.n_params},)"
            )
        if not (qs == (n,) or (len(qs) == 2 and qs[1] == n)):
            raise ValueError(f"error model {self.name!r}: q has shape {qs}, expected (N, {n})")
        N = qs[0] if len(qs) == 2 else 1
        if ps not in ((3,), (N, 3)):
            raise ValueError(
                f"error model {self.name!r}: p_flange has shape {ps}, expected (3,) or ({N}, 3)"
            )

    def column_scale(self, length: float) -> F64:
        """Roughly the metres a unit of each parameter moves the pin by, (P,).

        Identification scales its Jacobian columns (and the solver's steps) by it so
        every parameter weighs alike: ``length`` (the working radius) for radians,
        1 for metres. Models with other units override it.
        """
        return np.where(np.array(self.param_units) == "rad", float(length), 1.0)

    def zero(self) -> F64:
        """The nominal robot's parameter vector (all corrections zero)."""
        return np.zeros(self.n_params)

    @abstractmethod
    def pin_and_jacobian(
        self, x: ArrayLike, q: ArrayLike, p_flange: ArrayLike, *, jac: bool = True
    ) -> tuple[F64, F64, F64 | None]:
        """Points in the base frame and their Jacobian with respect to ``x``.

        Parameters
        ----------
        x : (P,) model parameters
        q : (N, n) joint vectors, columns in ``layout.names`` order
        p_flange : (N, 3) or (3,) points in the flange frame
        jac : also compute the Jacobian

        Returns
        -------
        p_base : (N, 3)
            ``T_base_flange(q_i; x) @ p_flange_i``.
        R_base_flange : (N, 3, 3)
            Rotation of the flange (the derivative of ``p_base`` w.r.t. ``p_flange``).
        J : (N, 3, P) or None
            ``d p_base / d x``.
        """

    @abstractmethod
    def origins(self, x: ArrayLike) -> dict[str, F64]:
        """New ``T_parent_joint`` of the actuated joints that reproduce the model at ``x``."""

    def chain(self, x: ArrayLike) -> Chain:
        """The corrected chain (base link to flange link) as a :class:`Chain`."""
        return self.nominal.with_origins(self.origins(x))


# ----------------------------------------------------------------------------- helpers


def as_points(p_flange: ArrayLike, N: int) -> F64:
    """Broadcast flange-frame points to ``(N, 3)``."""
    return np.broadcast_to(np.asarray(p_flange, dtype=float), (N, 3))


def so3_exp(r: ArrayLike) -> F64:
    """``exp([r]_x)`` for one rotation vector ``r`` (3,) -> (3, 3)."""
    r = np.asarray(r, dtype=float)
    K = _skew3(r)
    th = float(np.sqrt(r @ r))
    if th < 1e-12:
        return _I3 + K
    return _I3 + (np.sin(th) / th) * K + ((1.0 - np.cos(th)) / th**2) * (K @ K)


def _skew3(r: F64) -> F64:
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


def so3_right_jacobian(r: ArrayLike) -> F64:
    """Right Jacobian of SO(3): ``exp([r + dr]) = exp([r]) exp([J_r(r) dr])`` to first order.

    ``J_r = I - (1 - cos t)/t^2 [r] + (t - sin t)/t^3 [r]^2`` (Chirikjian 2011,
    eq. 10.86), with its series near ``t = 0``.
    """
    r = np.asarray(r, dtype=float)
    t = float(np.sqrt(r @ r))
    K = _skew3(r)
    if t < 1e-6:
        return _I3 - 0.5 * K + (1.0 / 6.0) * (K @ K)
    return _I3 - (1 - np.cos(t)) / t**2 * K + (t - np.sin(t)) / t**3 * (K @ K)


def translation(p: ArrayLike) -> F64:
    T = _I4.copy()
    T[:3, 3] = np.asarray(p, dtype=float)
    return T


def rotation(R: ArrayLike) -> F64:
    T = _I4.copy()
    T[:3, :3] = np.asarray(R, dtype=float)
    return T


def motion(axis: F64, prismatic: bool, qk: F64) -> F64:
    """Joint motion ``M(q)`` for a batch ``(N,) -> (N, 4, 4)``.

    Revolute: ``Rot(a, q) = I + sin(q) K + (1 - cos(q)) K^2`` with ``K = [a]_x``
    (Rodrigues); prismatic: ``Trans(q a)``.
    """
    M = np.zeros(qk.shape + (4, 4))
    M[:, 3, 3] = 1.0
    if prismatic:
        M[:, 0, 0] = M[:, 1, 1] = M[:, 2, 2] = 1.0
        M[:, :3, 3] = qk[:, None] * axis
    else:
        K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
        M[:, :3, :3] = (
            np.eye(3) + np.sin(qk)[:, None, None] * K + (1.0 - np.cos(qk))[:, None, None] * (K @ K)
        )
    return M


def joint_motions(axis: F64, prismatic: np.ndarray, q: F64) -> F64:
    """Every joint's motion at once: ``q (N, n) -> M (N, n, 4, 4)``, ``M[:, k] = M_k(q[:, k])``.

    The same Rodrigues formula as :func:`motion` (``I + sin(q) K + (1 - cos(q)) K^2``
    with ``K = [axis_k]_x`` for a revolute joint, ``Trans(q axis_k)`` for a
    prismatic one), evaluated for all joints in one pass instead of one call per
    joint (the error models' kinematics run hundreds of times a fit).

    Parameters
    ----------
    axis : (n, 3) unit joint axes
    prismatic : (n,) bool
    q : (N, n) joint values (rad or m)
    """
    K = skew(axis)
    rev = ~np.asarray(prismatic, dtype=bool)
    s = np.where(rev, np.sin(q), 0.0)[..., None, None]
    c = np.where(rev, 1.0 - np.cos(q), 0.0)[..., None, None]
    M = np.zeros(q.shape + (4, 4))
    M[..., 3, 3] = 1.0
    M[..., :3, :3] = _I3 + s * K + c * (K @ K)
    M[..., :3, 3] = np.where(rev[:, None], 0.0, q[..., None] * axis)
    return M


def so3_exp_many(r: F64) -> F64:
    """:func:`so3_exp` of a stack of rotation vectors, ``(n, 3) -> (n, 3, 3)``."""
    K = skew(r)
    th = np.sqrt(np.einsum("ki,ki->k", r, r))
    big = th >= 1e-12
    ts = np.where(big, th, 1.0)
    a = np.where(big, np.sin(ts) / ts, 1.0)[:, None, None]
    b = np.where(big, (1.0 - np.cos(ts)) / ts**2, 0.0)[:, None, None]
    return _I3 + a * K + b * (K @ K)


def so3_right_jacobian_many(r: F64) -> F64:
    """:func:`so3_right_jacobian` of a stack of rotation vectors, ``(n, 3) -> (n, 3, 3)``.

    ``J_r = I - (1 - cos t)/t^2 [r] + (t - sin t)/t^3 [r]^2`` (Chirikjian 2011,
    eq. 10.86), the series ``I - [r]/2 + [r]^2/6`` below ``t = 1e-6``.
    """
    K = skew(r)
    t = np.sqrt(np.einsum("ki,ki->k", r, r))
    big = t >= 1e-6
    ts = np.where(big, t, 1.0)
    a = np.where(big, (1 - np.cos(ts)) / ts**2, 0.5)[:, None, None]
    b = np.where(big, (ts - np.sin(ts)) / ts**3, 1.0 / 6.0)[:, None, None]
    return _I3 - a * K + b * (K @ K)


def point_motion(T_base_F: F64, twists: F64, p_base: F64) -> F64:
    """Equation (1): point velocities for local twists at a frame.

    Leading dimensions broadcast, so one call serves every factor of a chain
    (``T_base_F`` (K, N, 4, 4) with ``twists`` (K, 1, 6, m)).

    Parameters
    ----------
    T_base_F : (..., N, 4, 4) base pose of the frame the twists act at
    twists : (..., 6, m) or (..., N, 6, m) local twists ``(v; w)`` in frame F, one per column
    p_base : (N, 3) points moved by the factor

    Returns
    -------
    (..., N, 3, m) ``R v + (R w) x (p - o)``.
    """
    R = T_base_F[..., :3, :3]
    v = R @ twists[..., :3, :]
    w = R @ twists[..., 3:, :]
    d = p_base - T_base_F[..., :3, 3]
    dx, dy, dz = d[..., 0, None], d[..., 1, None], d[..., 2, None]
    out = np.empty_like(v)
    out[..., 0, :] = v[..., 0, :] + w[..., 1, :] * dz - w[..., 2, :] * dy
    out[..., 1, :] = v[..., 1, :] + w[..., 2, :] * dx - w[..., 0, :] * dz
    out[..., 2, :] = v[..., 2, :] + w[..., 0, :] * dy - w[..., 1, :] * dx
    return out


def rmul(T: F64, C: F64) -> F64:
    """``T @ C`` for a batch ``T (N, 4, 4)`` and a constant ``C (4, 4)``."""
    return T @ C


ModelFactory = Callable[[Chain], ErrorModel]
