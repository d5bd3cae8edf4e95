"""`vtcal export`: every format read back by an independent reader matches vtcal's FK to 1e-9 m.

Readers written here, from the formats' own definitions (not vtcal's code):
yourdfpy for the URDF; ur_description's composition of the UR kinematics YAML
(``Rz(pi) prod [Trans RPY Rz(q)] T_wrist3_flange T_flange_tool0``); modified-DH
forward kinematics with Hayati's beta; the offsets as ``q + dq0`` on the
nominal robot. Run folders are small: ``vtcal identify`` on the sample's
converged touch-ups (the ``lrmate_run`` fixture of conftest.py, about a
second), or a calibrated.urdf written from a known perturbation.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.cli import main
from pipeline.errors import ExportRefused
from pipeline.export.calibration import load_run
from pipeline.export.dh import mdh_table
from pipeline.kinematics import fk, load_chain
from pipeline.kinematics.urdf_write import write_calibrated_urdf
from pipeline.models import get_model
from pipeline.robots import builtin_urdf

REPO = Path(__file__).resolve().parent.parent
TRUTH = REPO / "datasets" / "samples" / "sample_lrmate.mcap.truth.json"
TOL = 1e-9

# ur_description's UR5e default kinematics and its fixed frames (facts of that package)
UR5E = """<?xml version="1.0"?>
<robot name="ur5e_nominal">
  <link name="base_link"/><link name="base_link_inertia"/><link name="shoulder_link"/>
  <link name="upper_arm_link"/><link name="forearm_link"/><link name="wrist_1_link"/>
  <link name="wrist_2_link"/><link name="wrist_3_link"/><link name="flange"/><link name="tool0"/>
  <joint name="base_link-base_link_inertia" type="fixed"><parent link="base_link"/>
    <child link="base_link_inertia"/><origin xyz="0 0 0" rpy="0 0 3.141592653589793"/></joint>
  {joints}
  <joint name="wrist_3-flange" type="fixed"><parent link="wrist_3_link"/><child link="flange"/>
    <origin xyz="0 0 0" rpy="0 -1.5707963267948966 -1.5707963267948966"/></joint>
  <joint name="flange-tool0" type="fixed"><parent link="flange"/><child link="tool0"/>
    <origin xyz="0 0 0" rpy="1.5707963267948966 0 1.5707963267948966"/></joint>
</robot>
"""
UR5E_ORIGINS = [  # (joint, parent, child, xyz, rpy)
    ("shoulder_pan_joint", "base_link_inertia", "shoulder_link", "0 0 0.1625", "0 0 0"),
    ("shoulder_lift_joint", "shoulder_link", "upper_arm_link", "0 0 0", "1.570796327 0 0"),
    ("elbow_joint", "upper_arm_link", "forearm_link", "-0.425 0 0", "0 0 0"),
    ("wrist_1_joint", "forearm_link", "wrist_1_link", "-0.3922 0 0.1333", "0 0 0"),
    ("wrist_2_joint", "wrist_1_link", "wrist_2_link", "0 -0.0997 0", "1.570796327 0 0"),
    ("wrist_3_joint", "wrist_2_link", "wrist_3_link", "0 0.0996 0",
     "1.570796327 3.141592653589793 3.141592653589793"),
]  # fmt: skip


def ur5e_urdf() -> str:
    joints = "\n  ".join(
        f'<joint name="{n}" type="revolute"><parent link="{p}"/><child link="{c}"/>'
        f'<origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="0 0 1"/>'
        '<limit lower="-6.28" upper="6.28" effort="1" velocity="1"/></joint>'
        for n, p, c, xyz, rpy in UR5E_ORIGINS
    )
    return UR5E.replace("{joints}", joints)


# ----------------------------------------------------------------- independent maths


def rx(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def ry(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def rz(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def tr(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def xyz_rpy(x, y, z, r, p, w) -> np.ndarray:
    return tr(x, y, z) @ rz(w) @ ry(p) @ rx(r)


def ur_fk(kin: dict, q: np.ndarray, end: str) -> np.ndarray:
    """ur_description's composition of the kinematics YAML, base_link -> flange or tool0."""
    T = rz(np.pi)
    for k, seg in enumerate(("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")):
        e = kin[seg]
        T = T @ xyz_rpy(e["x"], e["y"], e["z"], e["roll"], e["pitch"], e["yaw"]) @ rz(q[k])
    T = T @ xyz_rpy(0, 0, 0, 0, -np.pi / 2, -np.pi / 2)
    if end == "tool0":
        T = T @ xyz_rpy(0, 0, 0, np.pi / 2, 0, np.pi / 2)
    return T


def mdh_fk(base: np.ndarray, rows: list, tool: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Modified DH with Hayati's beta: Rx(alpha) Ry(beta) Tx(a) Rz(theta + q) Tz(d)."""
    T = base
    for (alpha, beta, a, theta, d), qi in zip(rows, q, strict=True):
        T = T @ rx(alpha) @ ry(beta) @ tr(a, 0, 0) @ rz(theta + qi) @ tr(0, 0, d)
    return T @ tool


def read_dh_text(text: str) -> tuple[np.ndarray, list, np.ndarray, list[str]]:
    base = tool = None
    rows, names = [], []
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        if parts[0] == "BASE":
            base = xyz_rpy(*map(float, parts[1:7]))
        elif parts[0] == "TOOL":
            tool = xyz_rpy(*map(float, parts[1:7]))
        else:
            names.append(parts[0])
            rows.append([float(v) for v in parts[1:6]])
    assert base is not None and tool is not None
    return base, rows, tool, names


# ----------------------------------------------------------------- run folders


def _export(run: Path, fmt: str, out: Path, *extra: str) -> int:
    try:
        main(["export", str(run), "--format", fmt, "--out", str(out), *extra])
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def perturbed_run(tmp: Path, urdf: str, tip: str, seed: int, scale: float = 2e-3) -> Path:
    """A run folder whose calibrated.urdf is ``urdf`` with a random `full` perturbation."""
    chain = load_chain(urdf, "base_link", tip)
    model = get_model("full")(chain)
    x = np.random.default_rng(seed).normal(0, scale, model.n_params)
    tmp.mkdir(parents=True, exist_ok=True)
    pin = [0.01, -0.02, 0.15]
    (tmp / "calibrated.urdf").write_text(write_calibrated_urdf(urdf, model.origins(x), tip, pin))
    (tmp / "identify.json").write_text(json.dumps({"best_model": "full", "scale_held": True}))
    return tmp


def _q(n: int, seed: int = 7, N: int = 200) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-np.pi, np.pi, (N, n))


# ----------------------------------------------------------------- urdf


def test_urdf_export_roundtrips_with_yourdfpy(lrmate_run: Path, tmp_path: Path) -> None:
    yourdfpy = pytest.importorskip("yourdfpy")
    out = tmp_path / "c.urdf"
    assert _export(lrmate_run, "urdf", out) == 0
    assert out.read_bytes() == (lrmate_run / "calibrated.urdf").read_bytes()
    cal = load_run(lrmate_run)
    robot = yourdfpy.URDF.load(str(out), build_scene_graph=True, load_meshes=False)
    q = _q(6, N=40)
    want = fk(cal.chain, q)
    pin = want[:, :3, :3] @ cal.p_flange_pin + want[:, :3, 3]
    for i, qi in enumerate(q):
        robot.update_cfg(dict(zip(cal.chain.joint_names, qi, strict=True)))
        assert np.abs(robot.get_transform("flange", "base_link") - want[i]).max() < TOL
        assert np.abs(robot.get_transform("virtual_pin", "base_link")[:3, 3] - pin[i]).max() < TOL


# ----------------------------------------------------------------- ur-calibration


def test_ur_export_of_nominal_ur5e_gives_the_description_origins(tmp_path: Path) -> None:
    from pipeline.export.ur import ur_entries

    urdf = ur5e_urdf()
    chain = load_chain(urdf, "base_link", "tool0")
    entries, end = ur_entries(chain)
    assert end == "tool0"
    for (seg, (xyz, rpy)), (_, _, _, x0, r0) in zip(entries.items(), UR5E_ORIGINS, strict=True):
        got = xyz_rpy(*xyz, *rpy)
        want = xyz_rpy(*map(float, x0.split()), *map(float, r0.split()))
        assert np.abs(got - want).max() < 1e-12, seg


@pytest.mark.parametrize(
    ("robot", "tip", "end"), [("ur_description", "tool0", "tool0"), ("ur5e", "flange", "tool0")]
)
def test_ur_yaml_roundtrips(robot: str, tip: str, end: str, tmp_path: Path) -> None:
    urdf = ur5e_urdf() if robot == "ur_description" else builtin_urdf("ur5e")
    run = perturbed_run(tmp_path / "run", urdf, tip, seed=1)
    out = tmp_path / "ur.yaml"
    assert _export(run, "ur-calibration", out) == 0
    doc = yaml.safe_load(out.read_text())
    kin = doc["kinematics"]
    assert str(kin["hash"]).startswith("calib_")
    cal = load_run(run)
    q = _q(6)
    got = np.array([ur_fk(kin, qi, end) for qi in q])
    assert np.abs(got - fk(cal.chain, q)).max() < TOL


@pytest.mark.parametrize("robot", ["lrmate", "iiwa7"])
def test_ur_export_refuses_other_robots(robot: str, tmp_path: Path, capsys) -> None:
    run = perturbed_run(tmp_path / "run", builtin_urdf(robot), "flange", seed=2)
    out = tmp_path / "ur.yaml"
    assert _export(run, "ur-calibration", out) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("vtcal: error: ") and str(run) in err[0]
    assert not out.exists()


# ----------------------------------------------------------------- dh


@pytest.mark.parametrize("robot", ["lrmate", "ur5e", "iiwa7"])
def test_dh_roundtrips(robot: str, tmp_path: Path) -> None:
    run = perturbed_run(tmp_path / "run", builtin_urdf(robot), "flange", seed=3)
    out = tmp_path / "dh.txt"
    assert _export(run, "dh", out) == 0
    base, rows, tool, names = read_dh_text(out.read_text())
    cal = load_run(run)
    assert names == cal.chain.joint_names
    q = _q(len(names))
    got = np.array([mdh_fk(base, rows, tool, qi) for qi in q])
    assert np.abs(got - fk(cal.chain, q)).max() < TOL
    # Hayati's beta exactly where the nominal axes are parallel, bounded parameters
    hayati = [int(line.split()[-1]) for line in out.read_text().splitlines()
              if line.split() and line.split()[0] in names]  # fmt: skip
    parallel = {"lrmate": [0, 0, 1, 0, 0, 0], "ur5e": [0, 0, 1, 1, 0, 0]}
    if robot in parallel:
        assert hayati == parallel[robot]
    assert max(abs(r[2]) + abs(r[4]) for r in rows) < 2.0  # metres: no runaway d


def test_dh_refuses_a_prismatic_joint() -> None:
    urdf = """<robot name="p"><link name="base_link"/><link name="a"/><link name="flange"/>
      <joint name="j1" type="revolute"><parent link="base_link"/><child link="a"/>
        <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
      <joint name="j2" type="prismatic"><parent link="a"/><child link="flange"/>
        <axis xyz="1 0 0"/><limit lower="0" upper="1" effort="1" velocity="1"/></joint></robot>"""
    with pytest.raises(ExportRefused, match="prismatic"):
        mdh_table(load_chain(urdf, "base_link", "flange"))


# ----------------------------------------------------------------- offsets


def test_offsets_roundtrip_on_the_nominal_robot(lrmate_run: Path, tmp_path: Path, capsys) -> None:
    yourdfpy = pytest.importorskip("yourdfpy")
    out, flipped = tmp_path / "off.yaml", tmp_path / "off_signs.yaml"
    assert _export(lrmate_run, "offsets", out) == 0
    err = capsys.readouterr().err
    summary = json.loads((lrmate_run / "identify.json").read_text())
    held = summary["crossval"]["models"]["offsets"]["kfold_rms_mm"]
    assert f"{held:.4f} mm with offsets only" in err  # the cost of dropping the geometry
    doc = yaml.safe_load(out.read_text())
    off = np.array([j["offset_rad"] for j in doc["joints"]])
    assert np.allclose(np.degrees(off), [j["offset_deg"] for j in doc["joints"]], atol=1e-12)
    tcp = np.array(doc["tcp_flange_m"])
    # vtcal's offsets model, from its own artefact rows
    nominal_xml = (lrmate_run.parent / "nominal.urdf").read_text()
    params = pd.read_parquet(lrmate_run / "parameters.parquet")
    rows = params[params["model"] == "offsets"].set_index("name")
    model = get_model("offsets")(load_chain(nominal_xml, "base_link", "flange"))
    x = np.array([rows.loc[n, "value"] for n in model.param_names])
    pin = rows.loc[["pin.x", "pin.y", "pin.z"], "value"].to_numpy(dtype=float)
    q = _q(6, N=40)
    want, _, _ = model.pin_and_jacobian(x, q, pin, jac=False)
    robot = yourdfpy.URDF.load(io.StringIO(nominal_xml), build_scene_graph=True, load_meshes=False)
    names = [j["name"] for j in doc["joints"]]
    for i, qi in enumerate(q):
        robot.update_cfg(dict(zip(names, qi + off, strict=True)))  # q_true = q_reported + offset
        T = robot.get_transform("flange", "base_link")
        assert np.abs(T[:3, :3] @ tcp + T[:3, 3] - want[i]).max() < TOL
    # a controller counting joint_3 the other way gets the offset with the other sign
    assert _export(lrmate_run, "offsets", flipped, "--joint-signs", "1,1,-1,1,1,1") == 0
    back = yaml.safe_load(flipped.read_text())["joints"]
    signs = np.array([j["sign"] for j in back])
    assert list(signs) == [1, 1, -1, 1, 1, 1]
    q_controller = signs * q[0]
    q_true = signs * (q_controller + np.array([j["offset_rad"] for j in back]))
    assert np.allclose(q_true, q[0] + off, atol=1e-15)


def test_offsets_bad_signs_is_bad_input(lrmate_run: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "x.yaml"
    assert _export(lrmate_run, "offsets", out, "--joint-signs", "1,1,2,1,1,1") == 2
    assert "--joint-signs" in capsys.readouterr().err and not out.exists()


# ----------------------------------------------------------------- json, bad input


def test_json_holds_every_format_and_roundtrips(lrmate_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "all.json"
    assert _export(lrmate_run, "json", out) == 0
    doc = json.loads(out.read_text())
    cal = load_run(lrmate_run)
    assert doc["model"] == cal.model and doc["urdf"] == cal.calibrated_urdf
    assert "refused" in doc["ur_calibration"]  # the LR Mate's flange is not UR-like
    q = _q(6)
    rows = [[r[k] for k in ("alpha", "beta", "a", "theta", "d")] for r in doc["dh"]["rows"]]
    base, tool = np.array(doc["dh"]["base"]), np.array(doc["dh"]["tool"])
    got = np.array([mdh_fk(base, rows, tool, qi) for qi in q])
    assert np.abs(got - fk(cal.chain, q)).max() < TOL
    assert [j["name"] for j in doc["offsets"]["joints"]] == cal.chain.joint_names


def test_json_ur_entries_roundtrip(tmp_path: Path) -> None:
    run = perturbed_run(tmp_path / "run", ur5e_urdf(), "tool0", seed=4)
    out = tmp_path / "all.json"
    assert _export(run, "json", out) == 0
    doc = json.loads(out.read_text())
    assert doc["offsets"] == {"refused": doc["offsets"]["refused"]}  # no offsets model here
    ur = doc["ur_calibration"]
    q = _q(6)
    got = np.array([ur_fk(ur["entries"], qi, ur["end_frame"]) for qi in q])
    assert np.abs(got - fk(load_run(run).chain, q)).max() < TOL


def test_export_of_a_missing_run_is_bad_input(tmp_path: Path, capsys) -> None:
    assert _export(tmp_path / "nope", "dh", tmp_path / "x.txt") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0]
