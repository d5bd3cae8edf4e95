"""Whether the run's accuracy figure can be trusted: the model-adequacy test and the assumptions.

Cross-validation and the covariance both measure the *random* error of a fit.
A systematic input error that varies from pose to pose (a camera curve nobody
declared, defocus and a lamp's beam that change the apparent size with the
view, a print's shape the model does not hold) bends every touch-up a little
differently; the fit absorbs part of it and the held-out figure sees only the
rest. What it cannot hide is the size of the fit's residual: with detection
noise as the only error, the training residual's RMS is predicted by the
touch-ups' measured noise (:mod:`pipeline.stages.touchups.noise`): the repeated
captures' scatter (N1)-(N2) plus the pose component the loop's small steps show
(N3)-(N4), which the captures at one pose cannot see::

    E |r|^2 = tr(Sigma_touchup) (3N - p) / (3N),   rms_pred = sqrt(E |r|^2)           (A1)

(``3N`` residual components, ``p`` unknowns: the fit's ``dof = 3N - p``). The
ratio ``rho = rms_fit / rms_pred`` is near 1 when the touch-ups hold nothing
but detection noise (measured: 0.88-1.57 on every ``benchmarks/bench_optics.py``
cell of seed 11, each optical effect alone and all together on both robots;
3.3-4.1 on cells whose sRGB images were read as linear) and grows with every
error that is fixed at one pose and varies between poses. Robot repeatability and joint-encoder noise, which the
captures at one pose cannot see, also raise it, which is why the bar is
``RATIO_MAX = 3``: 9 times the variance detection explains, a chi-square
excess far beyond chance at the tens of degrees of freedom of a calibration
(``dof >= 20``: ``P(chi2_dof / dof > 9) < 1e-30``), so a run that crosses it
carries an error of the same order as its noise or larger that no figure of
the run measures. The verdict then says "systematic error likely: the figure is
a lower bound" and a tolerance fails (:mod:`pipeline.accuracy.verdict`).

The assumptions: every input the accuracy hinges on that was neither declared
in the recording nor estimated with confidence (:func:`assumptions`), each one
line for the console, the report and ``identify.json``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

#: share of clipped edge pixels above which the figure is a lower bound (bench_optics'
#: "saturated" cell: 25 %, 1.0 mm off where the run said 0.08 mm)
SATURATED_LOWER_BOUND = 0.05

#: the fit's residual RMS above this multiple of what detection noise predicts (A1):
#: "systematic error likely"
RATIO_MAX = 3.0


def adequacy(summary: Mapping[str, Any], noise: Mapping[str, Any] | None) -> dict[str, Any]:
    """The model-adequacy test (A1) of a fit's summary against the captures' noise.

    Parameters
    ----------
    summary : identify's summary of the shipped model (``rms_mm``, ``dof``, ``n_rows``)
    noise : :func:`pipeline.stages.touchups.noise.capture_noise` of the recording, or None

    Returns
    -------
    dict: ``tested`` (bool), ``fit_mm``, ``predicted_mm``, ``ratio``, ``ratio_max``,
    ``systematic`` (bool: tested and ``ratio > ratio_max``) and ``note`` (one sentence).
    """
    fit = _num(summary.get("rms_mm"))
    dof, n = _num(summary.get("dof")), _num(summary.get("n_rows"))
    rms_touchup = _num((noise or {}).get("rms_touchup_um"))
    out: dict[str, Any] = {
        "tested": False,
        "fit_mm": fit,
        "predicted_mm": None,
        "ratio": None,
        "ratio_max": RATIO_MAX,
        "systematic": False,
    }
    if rms_touchup is None:
        out["note"] = (
            "model adequacy not tested: the recording has no repeated captures at a touch-up's "
            "final pose to measure the detection noise from"
        )
        return out
    if fit is None or dof is None or n is None or dof <= 0 or n <= 0:
        out["note"] = "model adequacy not tested: the fit has no residual degrees of freedom"
        return out
    pred = 1e-3 * rms_touchup * math.sqrt(dof / (3.0 * n))
    ratio = fit / pred if pred > 0 else math.inf
    systematic = ratio > RATIO_MAX
    out.update(tested=True, predicted_mm=pred, ratio=ratio, systematic=systematic)
    if systematic:
        out["note"] = (
            f"systematic error likely: the fit's residual ({fit:.4f} mm) is {ratio:.1f}x what "
            f"the touch-ups' measured noise predicts ({pred:.4f} mm: repeated captures and the "
            "loop's small steps); an error "
            "that changes from pose to pose (camera curve, focus, light, print) is in the "
            "touch-ups, and the figure is a lower bound"
        )
    else:
        out["note"] = (
            f"model adequate: the fit's residual ({fit:.4f} mm) is {ratio:.2f}x what the "
            f"touch-ups' measured noise predicts ({pred:.4f} mm: repeated captures and the "
            "loop's small steps; "
            f"<= {RATIO_MAX:g}x)"
        )
    return out


def assumptions(recording: Mapping[str, Any] | None) -> list[dict[str, Any]]:
    """What the accuracy hinges on that was assumed, from ingest's ``recording.json``.

    Returns
    -------
    list of ``{"key", "text", "lower_bound"}``: ``lower_bound`` when the assumption
    alone makes the run's figure a lower bound of its error: a curve the edges say is
    neither linear nor sRGB, a clipped edge. An assumed response (edges too sharp to
    read it) is said on the console only; where a wrong curve's bias varies from pose
    to pose the adequacy test finds it.
    """
    rec = recording or {}
    cam = rec.get("camera") or {}
    inferred = rec.get("inferred") or {}
    out: list[dict[str, Any]] = []
    if str(cam.get("response_source", "")) == "assumed":
        why = str(inferred.get("camera_response") or cam.get("note") or "")
        resp = cam.get("response", "linear")
        out.append(
            {
                "key": "camera_response",
                "text": f"camera response assumed {resp}: the figure holds only if the camera "
                f"is {resp} ({why})",
                # sharp edges, where it cannot be read, are also where it matters least;
                # the adequacy test catches a wrong curve whose bias varies with the pose
                "lower_bound": False,
            }
        )
    note = str(cam.get("note", ""))
    if cam.get("response_source") == "estimated" and "neither linear nor sRGB" in note:
        out.append(
            {
                "key": "camera_response",
                "text": f"the camera's curve is neither linear nor sRGB (best power law gamma "
                f"{float(cam.get('gamma_fit', float('nan'))):.2f}); {cam.get('response')} was "
                "used: a wrong curve biases every long axis alike, which no residual shows; "
                "declare it (camera_response)",
                "lower_bound": True,
            }
        )
    sat = float(cam.get("saturated_fraction") or 0.0)
    if sat > SATURATED_LOWER_BOUND:
        out.append(
            {
                "key": "saturation",
                "text": f"{100 * sat:.0f} % of the pixels at the target's edge are clipped: the "
                "long axes rest on a censored fit of the edge, less exact the more is clipped "
                "(lower the exposure)",
                "lower_bound": True,
            }
        )
    for key in ("designated_u", "designated_v"):
        text = str(inferred.get(key, ""))
        if "image centre" in text:
            out.append(
                {
                    "key": key,
                    "text": f"{key} assumed: {text} (not in the recording's metadata)",
                    "lower_bound": False,
                }
            )
    return out


def trust(
    summary: Mapping[str, Any],
    noise: Mapping[str, Any] | None,
    recording: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """``identify.json["trust"]``: the adequacy test, the assumptions and what they imply.

    ``lower_bound`` is true when the adequacy test found a systematic error or an
    assumption the figure hinges on was made; ``warnings`` are the console's lines.
    """
    test = adequacy(summary, noise)
    made = assumptions(recording)
    warnings = [a["text"] for a in made]
    if test["systematic"]:
        warnings.append(str(test["note"]))
    region = summary.get("region") or {}
    if region.get("extrapolation_warning"):  # pipeline.estimation.region (G1)
        warnings.append(str(region.get("note", "")))
    return {
        "adequacy": test,
        "assumptions": made,
        "lower_bound": bool(test["systematic"] or any(a["lower_bound"] for a in made)),
        "warnings": warnings,
    }


def _num(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None
