"""Touch-up extraction, step 3: the image Jacobian and what it tells of the camera.

One image Jacobian ``J`` (3 x 3, flange translation -> ``(du, dv, ds_inv)``) for
every target, fitted row by row by Huber-robust least squares from the pairs of
consecutive still captures a small pure flange translation apart (the estimator the
live loop uses too: :func:`pipeline.measurement.image_jacobian.fit_image_jacobian`),
its size row scaled per target only where a print is
measurably another size (:func:`size_row_scales`). A pair's change of ``(u, v,
s_inv)`` and the camera, diameter and view geometry a Jacobian implies are the
measurement model's (:mod:`pipeline.measurement.image`). The steps are described
in :mod:`pipeline.stages.touchups.stage`.
"""

from __future__ import annotations

import numpy as np


def pair_scatters(pair_seg: np.ndarray, dF: np.ndarray, n: int) -> np.ndarray:
    """Each touch-up's pair scatter ``S_i = sum_{p in i} v_p v_p^T``, ``(n, 3, 3)`` m^2.

    ``v_p`` the pairs' translations ``dF`` (``(N, 3)``), ``pair_seg`` their touch-up;
    what identification weighs the nominal-to-calibrated map with
    (:mod:`pipeline.estimation.correction_frame`, F2).
    """
    S = np.zeros((n, 3, 3))
    np.add.at(S, pair_seg, dF[:, :, None] * dF[:, None, :])
    return S


def size_row_scales(
    J: np.ndarray,
    dF: np.ndarray,
    dm: np.ndarray,
    groups: np.ndarray,
    *,
    sigmas: float,
    min_pairs: int,
) -> tuple[float, dict[int, tuple[float, float]]]:
    """Per-target scale of the image Jacobian's size row, with its standard error.

    A target of printed diameter ``D_k`` seen at the designated size has
    ``s_inv = z / (f D_k)``, so its size row is a common row times ``1 / D_k``;
    the centre rows do not depend on the target. Per target the least-squares
    scale of its pairs' size changes against the pooled row ``J_2``,

        c_k = sum(a_i b_i) / sum(a_i^2),  a_i = J_2 . dF_i,  b_i = dm_i,2,
        se(c_k) = sqrt(sum(r_i^2) / (n - 1) / sum(a_i^2)),

    is taken relative to the median target's, ``c_ref = median_k c_k`` (the
    pooled row mixes every print; the median is the prints that agree), and is
    kept where ``|c_k / c_ref - 1| > sigmas * se(c_k)``: a print measurably
    larger or smaller than the others. The rest take ``c_ref J_2``.

    Parameters
    ----------
    J : (3, 3) global image Jacobian
    dF : (N, 3) flange translations of the pairs (m)
    dm : (N, 3) their ``(u, v, s_inv)`` changes
    groups : (N,) target label of each pair

    Returns
    -------
    c_ref : the scale of the size row the targets share (1.0 with fewer than 2 targets)
    kept : ``{label: (c_k / c_ref, se)}`` for the targets whose own scale is kept
    """
    raw: dict[int, tuple[float, float]] = {}
    a_all = dF @ J[2]
    for g in np.unique(groups):
        m = groups == g
        if int(m.sum()) < min_pairs:
            continue
        a, b = a_all[m], dm[m, 2]
        saa = float(a @ a)
        if saa <= 0.0:
            continue
        c = float(a @ b) / saa
        r = b - c * a
        raw[int(g)] = (c, float(np.sqrt(float(r @ r) / max(len(a) - 1, 1) / saa)))
    if len(raw) < 2:
        return 1.0, {}
    c_ref = float(np.median([c for c, _ in raw.values()]))
    kept = {
        g: (c / c_ref, se / c_ref)
        for g, (c, se) in raw.items()
        if abs(c / c_ref - 1.0) > sigmas * se / c_ref
    }
    return c_ref, kept
