"""The touch-up measurement is defined once, in ``pipeline/measurement`` (issue 37).

The image side (``e_T = (u - u0, v - v0, 1/s - 1/s0)``, ``s = f D / z``, what an
image Jacobian implies) and eq. (1) (its layout, rows and linear pin/target
solve) live in :mod:`pipeline.measurement`; every stage, the live loop, the
simulator, the planner, validate and the report call them. The check reads the
sources (``ast``) of every other module of ``pipeline/`` and fails on a second
definition: a function or class of the core's names, an inverse-size difference
``1/a - 1/b``, or eq. (1)'s target-column arithmetic ``... + 3 + 3 * k``. The
simulator's truth (``sim/target_geometry.py``, the exact projected ellipse) stays
apart. Negative controls feed the check each kind of duplicate. Then the core
against known truth: the linear solve recovers an exact pin and targets, and
:func:`pipeline.measurement.pin.rows` are :class:`Problem`'s Jacobian rows.
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

import pipeline.measurement.image as image
import pipeline.measurement.pin as pin

PACKAGE = Path(__file__).resolve().parent.parent / "pipeline"
CORE = PACKAGE / "measurement"
#: the simulator's truth: the exact image of a printed disc, which the model approximates;
#: and its thin-lens optics, whose defocus ``1/z - 1/z_focus`` is no image size
APART = {
    PACKAGE / "sim" / "target_geometry.py",
    PACKAGE / "sim" / "optics_state.py",
    PACKAGE / "sim" / "render_pbr.py",
}


def _core_names() -> set[str]:
    names: set[str] = set()
    for p in CORE.glob("*.py"):
        for node in ast.parse(p.read_text()).body:
            if isinstance(node, ast.FunctionDef | ast.ClassDef) and not node.name.startswith("_"):
                names.add(node.name)
    return names


def _is_const(node: ast.AST, value: float) -> bool:
    return isinstance(node, ast.Constant) and node.value == value


def _reciprocal(node: ast.AST) -> bool:
    return isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div) and _is_const(node.left, 1)


def duplicates(text: str, core: set[str]) -> list[str]:
    """What of the measurement model one module's source defines again (one line each)."""
    out = []
    tree = ast.parse(text)
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.ClassDef) and node.name in core:
            out.append(f"line {node.lineno}: defines {node.name}")
    for node in ast.walk(tree):
        if not isinstance(node, ast.BinOp):
            continue
        if isinstance(node.op, ast.Sub) and _reciprocal(node.left) and _reciprocal(node.right):
            out.append(f"line {node.lineno}: inverse-size difference 1/a - 1/b")
        if (
            isinstance(node.op, ast.Add)
            and isinstance(node.right, ast.BinOp)
            and isinstance(node.right.op, ast.Mult)
            and _is_const(node.right.left, 3)
            and (
                _is_const(node.left, 3)
                or (
                    isinstance(node.left, ast.BinOp)
                    and isinstance(node.left.op, ast.Add)
                    and _is_const(node.left.right, 3)
                )
            )
        ):
            out.append(f"line {node.lineno}: eq. (1) target columns ... + 3 + 3 * k")
    return sorted(out, key=lambda line: int(line.split()[1].rstrip(":")))


def test_the_measurement_model_is_defined_once() -> None:
    core = _core_names()
    assert {"image_error", "pair_change", "camera_from_jacobian", "Problem", "rows"} <= core
    found = []
    for p in sorted(PACKAGE.rglob("*.py")):
        if p.is_relative_to(CORE) or p in APART:
            continue
        found += [f"{p.relative_to(PACKAGE.parent)} {d}" for d in duplicates(p.read_text(), core)]
    assert found == []


#: the core's modules whose functions may not be copied under other names: the measurement
#: model and the covariance of a fit (pipeline/estimation/uncertainty.py)
SHAPE_CORE = [*sorted(CORE.glob("*.py")), PACKAGE / "estimation" / "uncertainty.py"]
#: statements a copied run must hold to count (shorter runs are idioms, not the model)
SHAPE_MIN = 4


class _Shape(ast.NodeTransformer):
    """An AST with its names, arguments and constants blanked: what is left is its shape
    (the calls, attributes and operators), so a copy under other names matches."""

    def visit_Name(self, node: ast.Name) -> ast.AST:
        return ast.copy_location(ast.Name(id="_", ctx=node.ctx), node)

    def visit_arg(self, node: ast.arg) -> ast.AST:
        return ast.copy_location(ast.arg(arg="_"), node)

    def visit_Constant(self, node: ast.Constant) -> ast.AST:
        return ast.copy_location(ast.Constant(value=0), node)


def _runs(body: list[ast.stmt]) -> list[tuple[str, int]]:
    """Each window of ``SHAPE_MIN`` consecutive statements of ``body`` (and of every nested
    block) as its shape, with the first statement's line; docstrings left out."""
    out = []
    stmts = [b for b in body if not (isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant))]
    for i in range(len(stmts) - SHAPE_MIN + 1):
        window = stmts[i : i + SHAPE_MIN]
        text = "".join(ast.dump(_Shape().visit(ast.parse(ast.unparse(w)))) for w in window)
        out.append((text, window[0].lineno))
    for b in stmts:
        for field in ("body", "orelse", "finalbody"):
            inner = getattr(b, field, None)
            if isinstance(inner, list) and inner and isinstance(inner[0], ast.stmt):
                out += _runs(inner)
    return out


def _function_runs(text: str) -> list[tuple[str, int]]:
    """:func:`_runs` of every function body of a module's source."""
    out = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.FunctionDef):
            out += _runs(node.body)
    return out


def shape_copies(text: str, core_shapes: dict[str, str]) -> list[str]:
    """Runs of one module's statements that are a core run under other names (one line each)."""
    seen = {}
    for shape, line in _function_runs(text):
        if shape in core_shapes and line not in seen:
            seen[line] = f"line {line}: the shape of {core_shapes[shape]}"
    return [seen[k] for k in sorted(seen)]


def _core_shapes() -> dict[str, str]:
    out: dict[str, str] = {}
    for p in SHAPE_CORE:
        for shape, line in _function_runs(p.read_text()):
            out.setdefault(shape, f"{p.relative_to(PACKAGE.parent)}:{line}")
    return out


def test_the_core_is_not_copied_under_other_names() -> None:
    """No module repeats a run of the core's statements with other names and values."""
    core = _core_shapes()
    assert len(core) > 20
    found = []
    for p in sorted(PACKAGE.rglob("*.py")):
        if p in SHAPE_CORE or p in APART:
            continue
        found += [f"{p.relative_to(PACKAGE.parent)} {d}" for d in shape_copies(p.read_text(), core)]
    assert found == []


def test_the_shape_check_finds_a_renamed_copy() -> None:
    """A negative control: the covariance routine copied with every name changed is found,
    and the same statements reordered are not."""
    import inspect

    from pipeline.estimation.uncertainty import covariance

    src = inspect.getsource(covariance)
    for old, new in (("covariance", "my_cov"), ("sigma2", "s2"), ("scale", "w"), ("good", "k")):
        src = src.replace(old, new)
    src = src.replace("1e-12", "1e-10")
    found = shape_copies(src, _core_shapes())
    assert found and "uncertainty.py" in found[0]
    fn = ast.parse(src).body[0]
    assert isinstance(fn, ast.FunctionDef)
    fn.body = list(reversed(fn.body[1:]))  # the docstring out, the statements reversed
    shuffled = ast.unparse(fn)
    assert shape_copies(shuffled, _core_shapes()) == []


def _importers() -> set[str]:
    """Paths (under ``pipeline/`` and ``benchmarks/``) of the modules importing the core."""
    out = set()
    root = PACKAGE.parent
    for p in [*PACKAGE.rglob("*.py"), *(root / "benchmarks").glob("*.py")]:
        if p.is_relative_to(CORE):
            continue
        for node in ast.walk(ast.parse(p.read_text())):
            mod = node.module if isinstance(node, ast.ImportFrom) else None
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if (mod or "").startswith("pipeline.measurement") or any(
                n.startswith("pipeline.measurement") for n in names
            ):
                out.add(str(p.relative_to(root)))
    return out


def test_docs_list_every_caller() -> None:
    """docs/architecture.md names every module that imports the core (relative to pipeline/)."""
    doc = (PACKAGE.parent / "docs" / "architecture.md").read_text()
    section = doc[doc.index("## The measurement model") : doc.index("## Packages")]
    callers = _importers()
    assert len(callers) > 15
    missing = [c for c in sorted(callers) if f"`{c.removeprefix('pipeline/')}`" not in section]
    assert missing == []


def test_the_check_finds_each_kind_of_duplicate() -> None:
    core = _core_names()
    text = (
        "def camera_from_jacobian(J, s0):\n    return J\n"
        "e = [u - u0, v - v0, 1.0 / s - 1.0 / s0]\n"
        "c0 = nk + 3 + 3 * tcol[t]\n"
        "A[:, 3 + 3 * tk] = -1.0\n"
    )
    assert duplicates(text, core) == [
        "line 1: defines camera_from_jacobian",
        "line 3: inverse-size difference 1/a - 1/b",
        "line 4: eq. (1) target columns ... + 3 + 3 * k",
        "line 5: eq. (1) target columns ... + 3 + 3 * k",
    ]
    # what is not the model: an ellipse's perimeter, a row count
    assert duplicates("p = (1 + 3 * h)\nm = 3 * N + len(d)\n", core) == []


def test_the_linear_solve_recovers_an_exact_pin_and_targets() -> None:
    rng = np.random.default_rng(3)
    N, K = 12, 3
    R = np.linalg.qr(rng.normal(size=(N, 3, 3)))[0]
    p_pin = np.array([0.01, -0.02, 0.25])
    targets = rng.normal(size=(K, 3))
    tk = np.arange(N) % K
    p0 = targets[tk] - np.einsum("nij,j->ni", R, p_pin)  # R_i p + p0_i = c_k(i)
    got_pin, got_targets, r = pin.solve_pin_targets(R, p0, tk, K, rng.uniform(0.5, 2.0, N))
    assert np.allclose(got_pin, p_pin, atol=1e-12)
    assert np.allclose(got_targets, targets, atol=1e-12)
    assert np.abs(r).max() < 1e-12


def test_rows_are_the_problems_jacobian() -> None:
    from tests.test_estimation import _problem

    prob, z = _problem("full", whitened=True, gauge=False)
    x, p_pin, tg = prob.split(z)
    D = prob.data
    _, J = prob.full_eval(x, p_pin, tg)
    assert J is not None
    _, R, Jx = prob.model.pin_and_jacobian(x, D.q, p_pin + D.d)
    assert prob.W is not None and Jx is not None
    B = np.einsum("ab,ncb->nac", prob.W, R) * D.sw[:, None, None]
    A = pin.whitened_rows(prob.layout, B, Jx, R, D.tk).reshape(-1, prob.layout.n)
    assert np.array_equal(A, J[: 3 * len(D.q)])
    # the layout's target columns hold -B_i on each row's target, zero on the others
    lay = prob.layout
    k = int(D.tk[0])
    assert np.array_equal(A[:3, lay.target(k)], -B[0])
    others = np.setdiff1d(np.arange(lay.n_kin + 3, lay.n), lay.target_columns([k]))
    assert not A[:3, others].any()


def test_image_error_and_the_size_relation_agree() -> None:
    f, D, z = 2400.0, 0.02, 0.25
    s0 = image.size_from_depth(f, D, z)
    assert image.depth_from_size(f, D, s0) == z
    assert image.focal_from_size(s0, z, D) == f
    # 1 mm further: e_T's size component is the change of z / (f D), linear in depth
    s = image.size_from_depth(f, D, z + 1e-3)
    e = image.image_error(330.0, 238.0, s, 320.0, 240.0, s0)
    assert np.allclose(e, [10.0, -2.0, 1e-3 / (f * D)], rtol=1e-12)
    # taken at s0, a centre error is the lateral offset it stands for
    e_s = image.touchup_error(330.0, 238.0, s, 320.0, 240.0, s0, True)
    assert np.allclose(e_s[:2], e[:2] * s0 / s, rtol=1e-15)
