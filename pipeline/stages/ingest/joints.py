"""Joint states of a recording: grouped by name list, the chain's, and at every image.

Ingest (:mod:`pipeline.stages.ingest.stage`) keeps the joint-state messages grouped by
their name lists (:data:`JointGroups`, names without the ``joint_prefix``:
:func:`strip_prefix`). After the streaming pass it takes the names that are
actuated URDF joints (:func:`arm_joint_names`), the chain joints' positions
from messages of any name order, sorted by header stamp
(:func:`chain_joint_states`), every value of the joints outside the chain for
the guardrails (:func:`other_joints`), and the frames table
(:func:`frame_table`): at every image stamp

- the joint vector linearly interpolated at its ``header.stamp``
  (``q(t) = q_k + (t - t_k) / (t_{k+1} - t_k) (q_{k+1} - q_k)`` between the
  bracketing joint states, sorted by their own header stamps);
- a stillness measure: the largest joint speed ``max_j |dq_j/dt|`` over the
  finite differences of consecutive joint states within ``+- still_window_s``
  of the stamp, and the gap between the bracketing joint states.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.errors import BadInput
from pipeline.kinematics.urdf import RobotDescription
from pipeline.stages.ingest.row_buffer import RowBuffer
from pipeline.stages.ingest.types import IngestConfig

#: joint states grouped by their name lists: {names: (stamps, message indices, positions)}
JointGroups = dict[tuple[str, ...], tuple[RowBuffer, RowBuffer, RowBuffer]]


def strip_prefix(names: list[str], prefix: str) -> tuple[str, ...]:
    """Joint-state names without ``prefix`` (``robot1/joint_1 -> joint_1``); others as they are."""
    if not prefix:
        return tuple(names)
    k = len(prefix)
    return tuple(n[k:] if n.startswith(prefix) else n for n in names)


def arm_joint_names(
    path: str, robot: RobotDescription, names: list[str], config: IngestConfig
) -> list[str]:
    """The joint-state names that are actuated URDF joints (in the order first seen).

    Names the URDF does not have (a gripper's fingers, another robot's joints)
    are left to the caller to note. Raises BadInput when no name is an actuated
    URDF joint (wrong URDF, or a name prefix that ``--joint-prefix`` should strip).
    """
    act = [n for n, j in robot.joints.items() if j.actuated]
    arm = [n for n in names if n in act]
    if arm:
        return arm
    hint = ""
    prefixes = {n[: n.rfind("/") + 1] for n in names if "/" in n}
    if len(prefixes) == 1 and not config.joint_prefix:
        hint = f"; the names carry the prefix {prefixes.pop()!r}: give it with --joint-prefix"
    raise BadInput(
        f"{path}: {config.joint_topic} names joints {names} that the URDF on "
        f"{config.description_topic} does not have (URDF joints: {sorted(act)}){hint}"
    )


def other_joints(
    groups: JointGroups,
    chain_names: list[str],
) -> dict[str, np.ndarray]:
    """Every joint-state value of the joints outside the chain, by joint name (for the guardrails)."""
    out: dict[str, list[np.ndarray]] = {}
    for key, (_ts, _ks, ps) in groups.items():
        arr = ps.array()
        for k, name in enumerate(key):
            if name not in chain_names:
                out.setdefault(name, []).append(arr[:, k])
    return {n: np.concatenate(v) for n, v in out.items()}


def chain_joint_states(
    path: str,
    groups: JointGroups,
    chain_names: list[str],
    config: IngestConfig,
    warnings: list[str],
) -> tuple[np.ndarray, np.ndarray, int]:
    """The chain's joint positions from joint-state messages of any name order.

    Each message's positions are picked by name (``q_j = position[name.index(j)]``),
    so joint order and extra joints do not matter. Messages naming none of the
    chain joints (a gripper published on the same topic) are skipped and noted
    in ``warnings``.

    Returns
    -------
    J_t : (m,) int64, the stamps sorted (stable)
    Q : (m, n) float64, the chain joints at ``J_t`` (columns in ``chain_names`` order)
    n_back : how many stamps go backwards in message order

    Raises
    ------
    BadInput
        A message naming some but not all chain joints; a non-finite chain joint position.
    """
    idx: list[np.ndarray] = []
    stamps: list[np.ndarray] = []
    rows: list[np.ndarray] = []
    skipped = 0
    for key, buffers in groups.items():
        ts, ks, ps = (b.array() for b in buffers)
        have = [n for n in chain_names if n in key]
        if not have:
            skipped += len(ts)
            continue
        if len(have) < len(chain_names):
            missing = [n for n in chain_names if n not in key]
            raise BadInput(
                f"{path}: {config.joint_topic} message {ks[0]}: joints {missing} missing "
                f"(has {list(key)})"
            )
        cols = np.array([key.index(n) for n in chain_names])
        q = np.asarray(ps)[:, cols]
        bad = np.flatnonzero(~np.all(np.isfinite(q), axis=1))
        if bad.size:
            row = q[bad[0]]
            what = ", ".join(
                f"{n}={float(x)}"
                for n, x in zip(chain_names, row, strict=True)
                if not np.isfinite(x)
            )
            raise BadInput(
                f"{path}: {config.joint_topic} message {ks[bad[0]]}: non-finite position "
                f"{what} ({bad.size} of {len(q)} messages with this name list)"
            )
        idx.append(np.asarray(ks))
        stamps.append(np.asarray(ts, dtype=np.int64))
        rows.append(q)
    if skipped:
        warnings.append(
            f"{path}: {config.joint_topic}: {skipped} messages name none of the chain joints "
            f"{chain_names} (another device's joint states) and were skipped"
        )
    if not rows:
        raise BadInput(f"{path}: no joint states of the chain joints {chain_names}")
    k_all = np.concatenate(idx)
    t_all = np.concatenate(stamps)
    q_all = np.concatenate(rows)
    in_order = np.argsort(k_all, kind="stable")
    n_back = int(np.sum(np.diff(t_all[in_order]) < 0))
    if len(t_all) < 2:
        raise BadInput(
            f"{path}: only one joint state on {config.joint_topic}: at least two are needed to "
            "interpolate the joints at the image stamps"
        )
    o = in_order[np.argsort(t_all[in_order], kind="stable")]
    return t_all[o], q_all[o], n_back


def frame_table(
    stamps: np.ndarray,
    log_times: np.ndarray,
    J_t: np.ndarray,
    Q: np.ndarray,
    names: list[str],
    config: IngestConfig,
) -> pd.DataFrame:
    """Joint vector and stillness at every image stamp (see the module docstring)."""
    n = len(stamps)
    tq = (J_t - J_t[0]).astype(np.float64) * 1e-9
    ts = (stamps - J_t[0]).astype(np.float64) * 1e-9
    q_at = np.empty((n, Q.shape[1]))
    for j in range(Q.shape[1]):
        q_at[:, j] = np.interp(ts, tq, Q[:, j])
    k = np.searchsorted(J_t, stamps, side="right")  # J_t[k-1] <= t < J_t[k]
    before = np.clip(k - 1, 0, len(J_t) - 1)
    after = np.clip(k, 0, len(J_t) - 1)
    extrap = (k == 0) | (k == len(J_t))
    gap = np.where(extrap, -1, J_t[after] - J_t[before])
    near = np.minimum(np.abs(stamps - J_t[before]), np.abs(J_t[after] - stamps))
    # joint speed of consecutive states
    if len(J_t) > 1:
        dt = np.diff(tq)
        dq = np.abs(np.diff(Q, axis=0))
        spd = np.max(dq, axis=1) / np.where(dt > 0, dt, np.inf)
        tmid = 0.5 * (tq[1:] + tq[:-1])
    else:
        spd = np.zeros(0)
        tmid = np.zeros(0)
    w = config.still_window_s
    lo = np.searchsorted(tmid, ts - w, side="left")
    hi = np.searchsorted(tmid, ts + w, side="right")
    max_speed = np.array(
        [float(spd[a:b].max()) if b > a else np.nan for a, b in zip(lo, hi, strict=True)]
    )
    # no difference inside the window (gap): use the bracketing pair
    nan = ~np.isfinite(max_speed)
    if nan.any() and len(spd):
        max_speed[nan] = spd[np.clip(k[nan] - 1, 0, len(spd) - 1)]
    df = pd.DataFrame(
        {
            "frame_index": np.arange(n, dtype=np.int64),
            "stamp_ns": stamps.astype(np.int64),
            "log_time_ns": log_times.astype(np.int64),
            "max_joint_speed": max_speed,
            "joint_gap_ns": gap.astype(np.int64),
            "nearest_joint_dt_ns": near.astype(np.int64),
            "moving": max_speed > config.moving_speed_rad_s,
            "joint_gap": (gap > config.max_joint_gap_s * 1e9) | extrap,
            "extrapolated": extrap,
        }
    )
    for j, nm in enumerate(names):
        df[nm] = q_at[:, j]
    return df
