"""Import of URDF chains and DH tables, and export of calibrated models back to URDF.

Forward kinematics is checked against pinocchio (built from the same URDF), a direct numpy DH
implementation and the equivalent URDF; the export round trip against the perturbed model.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation

from cdra_jax import tool_pose
from cdra_jax.arm import apply_frame_errors, revolute
from cdra_jax.cli import main
from cdra_jax.io import load_model, loads_model
from cdra_jax.io.dh import DHFileError, dh_modified, dh_standard, loads_dh
from cdra_jax.io.urdf import UrdfFileError
from cdra_jax.workflows import export_urdf, import_dh, import_urdf

DATA = Path(__file__).parent / "data" / "urdf"
UR5, PANDA, SLIDER = DATA / "ur5_robot.urdf", DATA / "panda.urdf", DATA / "slider_arm.urdf"
CHAINS = [
    (UR5, "base_link", "ee_link"),
    (PANDA, "panda_link0", "panda_hand_tcp"),
    (PANDA, "panda_link0", "panda_leftfinger"),  # 7 revolute + the prismatic finger
    (SLIDER, "world", "tool"),  # revolute, prismatic (oblique axis), continuous, fixed joints
]
TOL_MM, TOL_R = 1e-9, 1e-12


def pinocchio_pose(path, base, tip, names, types, q):
    """Tip link pose in the base link frame (mm) by pinocchio; ``q`` in rad / mm."""
    model = pin.buildModelFromUrdf(str(path))
    data = model.createData()
    out = []
    for row in np.atleast_2d(q):
        qp = pin.neutral(model)
        for name, kind, v in zip(names, types, row, strict=True):
            j = model.joints[model.getJointId(name)]
            if j.nq == 2:  # continuous: (cos, sin)
                qp[j.idx_q : j.idx_q + 2] = [math.cos(v), math.sin(v)]
            else:
                qp[j.idx_q] = v / 1000.0 if kind == "prismatic" else v
        pin.framesForwardKinematics(model, data, qp)
        T = (
            data.oMf[model.getFrameId(base)].inverse() * data.oMf[model.getFrameId(tip)]
        ).homogeneous
        T = np.array(T)
        T[:3, 3] *= 1000.0
        out.append(T)
    return np.stack(out)


def random_states(arm, n=40, seed=0):
    lim = arm.state_limits
    u = np.random.default_rng(seed).random((n, arm.dof))
    return lim[:, 0] + u * (lim[:, 1] - lim[:, 0])


def fk_error(A, B):
    """Largest translation difference (mm) and rotation-matrix entry difference."""
    dp = np.abs(A[..., :3, 3] - B[..., :3, 3]).max()
    return dp, np.abs(A[..., :3, :3] - B[..., :3, :3]).max()


@pytest.mark.parametrize("path,base,tip", CHAINS, ids=lambda v: getattr(v, "name", v))
def test_urdf_import_matches_pinocchio(path, base, tip):
    imp = import_urdf(path, base, tip)
    arm = loads_model(imp.to_toml())  # through the model file, as the CLI writes it
    q = random_states(arm)
    types = imp.details["joint_types"]
    ref = pinocchio_pose(path, base, tip, arm.module_names, types, q)
    dp, dR = fk_error(np.asarray(tool_pose(arm, q)), ref)
    assert dp < TOL_MM and dR < TOL_R


def test_urdf_import_content():
    imp = import_urdf(SLIDER, "world", "tool")
    arm = imp.arm
    assert arm.module_names == ("turn", "slide", "spin")
    assert [m.kind for m in arm.modules] == ["revolute", "prismatic", "revolute"]
    assert arm.frame_names == ("world", "column", "carriage", "tool")
    assert arm.modules[0].limits == ((-2.5, 2.5),)
    assert np.allclose(arm.modules[1].limits, [(-50.0, 250.0)])  # mm
    assert np.allclose(arm.modules[2].limits, [(-math.pi, math.pi)])  # continuous
    assert np.allclose(np.asarray(arm.modules[1].axis), [0.6, 0.0, 0.8])
    assert imp.details["joints"] == ["mount", "turn", "column_top", "slide", "spin", "tool_joint"]

    # frame 1 (column) folds the fixed joint column_top and the origin of slide
    def origin(xyz, rpy):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()  # URDF rpy: fixed axes x, y, z
        T[:3, 3] = xyz
        return T

    F1 = origin([20.0, 0.0, 300.0], [math.pi / 2, 0.0, 0.2]) @ origin([0.0, 50.0, 0.0], [0, 0.3, 0])
    assert np.allclose(np.asarray(arm.frames[1]), F1, rtol=0, atol=1e-12)
    ur5 = import_urdf(UR5, "base_link", "wrist_3_link").arm
    assert np.allclose(np.asarray(ur5.frames[-1]), np.eye(4))  # tip = last joint's child
    assert "plot" in dir(imp) and imp.plot() is not None
    assert imp.to_dict()["base"] == "world" and "ur5" not in imp.report()


# ---------------------------------------------------------------------------------- DH tables

UR5_DH = """# UR5, standard DH (a, d in mm; alpha, theta in rad)
joint,type,a,alpha,d,theta,lower,upper
shoulder_pan,revolute,0,1.5707963267948966,89.159,0,-3.14159,3.14159
shoulder_lift,revolute,-425,0,0,0,,
elbow,revolute,-392.25,0,0,0.3,-3.0,3.0
wrist_1,revolute,0,1.5707963267948966,109.15,0,-3.14159,3.14159
lift,prismatic,10,-1.5707963267948966,94.65,0.2,-50,150
wrist_3,revolute,0,0,82.3,-0.1,-3.14159,3.14159
"""


def dh_fk(rows, convention, q):
    T = np.eye(4)
    for r, v in zip(rows, q, strict=True):
        theta = r.theta + (v if r.kind == "revolute" else 0.0)
        d = r.d + (v if r.kind == "prismatic" else 0.0)
        T = T @ (dh_standard if convention == "standard" else dh_modified)(r.a, r.alpha, d, theta)
    return T


def urdf_from_dh(rows, convention, robot="dh_equivalent"):
    """The URDF of a DH chain (links L0..LK, joint i between L(i-1) and Li), built independently
    of cdra_jax: standard -> joint i at DH frame i-1 (origin A_{i-1}), modified -> at frame i."""
    parts = [f'<robot name="{robot}">'] + [f'<link name="L{i}"/>' for i in range(len(rows) + 1)]
    prev = np.eye(4)
    for i, r in enumerate(rows, start=1):
        if convention == "standard":
            origin = prev
            prev = dh_standard(r.a, r.alpha, r.d, r.theta)
        else:
            origin = dh_modified(r.a, r.alpha, r.d, r.theta)
        rpy = Rotation.from_matrix(origin[:3, :3]).as_euler("xyz")
        xyz = origin[:3, 3] / 1000.0
        lo, hi = r.limits or ((-math.pi, math.pi) if r.kind == "revolute" else (-100, 100))
        s = 1000.0 if r.kind == "prismatic" else 1.0
        parts.append(
            f'<joint name="{r.joint}" type="{r.kind}"><parent link="L{i - 1}"/>'
            f'<child link="L{i}"/><origin xyz="{" ".join(map(repr, xyz.tolist()))}" '
            f'rpy="{" ".join(map(repr, rpy.tolist()))}"/><axis xyz="0 0 1"/>'
            f'<limit lower="{lo / s!r}" upper="{hi / s!r}" effort="1" velocity="1"/></joint>'
        )
    n = len(rows)
    if convention == "standard":  # the last link's transform to the tool link
        rpy = Rotation.from_matrix(prev[:3, :3]).as_euler("xyz")
        xyz = prev[:3, 3] / 1000.0
        parts.append(
            f'<link name="tool"/><joint name="tool_fixed" type="fixed"><parent link="L{n}"/>'
            f'<child link="tool"/><origin xyz="{" ".join(map(repr, xyz.tolist()))}" '
            f'rpy="{" ".join(map(repr, rpy.tolist()))}"/></joint>'
        )
    else:
        parts.append(
            f'<link name="tool"/><joint name="tool_fixed" type="fixed"><parent link="L{n}"/>'
            '<child link="tool"/></joint>'
        )
    return "\n".join(parts + ["</robot>"])


@pytest.mark.parametrize("convention", ["standard", "modified"])
def test_dh_import_matches_direct_dh_and_urdf(tmp_path, convention):
    table = tmp_path / "ur5_dh.csv"
    table.write_text(UR5_DH)
    rows = loads_dh(UR5_DH)
    imp = import_dh(table, convention)
    arm = load_model(imp.save(tmp_path / "m.toml"))
    assert arm.module_names == tuple(r.joint for r in rows)
    assert arm.modules[4].kind == "prismatic" and arm.modules[4].limits == ((-50.0, 150.0),)
    assert arm.modules[1].limits == ((-math.pi, math.pi),)  # empty cells: default
    q = random_states(arm, 30, seed=1)
    T = np.asarray(tool_pose(arm, q))
    direct = np.stack([dh_fk(rows, convention, v) for v in q])
    dp, dR = fk_error(T, direct)
    assert dp < TOL_MM and dR < TOL_R
    urdf = tmp_path / "dh.urdf"
    urdf.write_text(urdf_from_dh(rows, convention))
    via_urdf = import_urdf(urdf, "L0", "tool").arm
    dp, dR = fk_error(np.asarray(tool_pose(via_urdf, q)), direct)
    assert dp < TOL_MM and dR < TOL_R
    types = [r.kind for r in rows]
    ref = pinocchio_pose(urdf, "L0", "tool", arm.module_names, types, q)
    dp, dR = fk_error(T, ref)
    assert dp < TOL_MM and dR < TOL_R


# ------------------------------------------------------------------------------------- export


def perturbed(arm, seed=3, scale=0.01):
    X = np.random.default_rng(seed).normal(size=arm.n_params) * scale
    X[0::6] *= 100.0  # translations: about 1 mm
    return apply_frame_errors(arm, X)


@pytest.mark.parametrize("path,base,tip", CHAINS[:2] + CHAINS[3:], ids=["ur5", "panda", "slider"])
def test_export_round_trip(tmp_path, path, base, tip):
    arm = perturbed(import_urdf(path, base, tip).arm)
    exp = export_urdf(arm, path, base, tip)
    assert exp.check_mm < 1e-9 and exp.check_rad < 1e-12
    out = exp.save(tmp_path / "cal.urdf")
    back = import_urdf(out, base, tip)
    q = random_states(arm, 20, seed=2)
    T = np.asarray(tool_pose(arm, q))
    dp, dR = fk_error(np.asarray(tool_pose(back.arm, q)), T)
    assert dp < TOL_MM and dR < TOL_R
    ref = pinocchio_pose(out, base, tip, arm.module_names, back.details["joint_types"], q)
    dp, dR = fk_error(ref, T)
    assert dp < TOL_MM and dR < TOL_R
    # the nominal chain is not the calibrated one (the test would pass trivially otherwise)
    nominal = import_urdf(path, base, tip).arm
    assert fk_error(np.asarray(tool_pose(nominal, q)), T)[0] > 0.1


def test_export_keeps_the_rest_of_the_file(tmp_path):
    arm = perturbed(import_urdf(UR5, "base_link", "ee_link").arm)
    text = export_urdf(arm, UR5, "base_link", "ee_link").text
    assert text.count("<transmission") == 6 and "hardware_interface/PositionJointInterface" in text
    assert 'name="tool0"' in text and 'name="world"' in text  # links off the chain
    assert "cdra-jax" in text.split("<link")[0]  # the XML comment at the top
    slider = perturbed(import_urdf(SLIDER, "world", "tool").arm)
    exp = export_urdf(slider, SLIDER, "world", "tool")
    assert '<mimic joint="finger"' in exp.text  # yourdfpy does not write it: copied over
    assert 'filename="package://slider_arm/meshes/base.stl"' in exp.text
    assert any("XML comment" in w for w in exp.warnings())


def test_export_tool_frame_without_a_joint_adds_a_link(tmp_path):
    arm = perturbed(import_urdf(SLIDER, "world", "flange").arm)
    exp = export_urdf(arm, SLIDER, "world", "flange")
    assert exp.tool_link == "flange_calibrated"
    assert any("flange_calibrated" in c for c in exp.changes)
    back = import_urdf(exp.save(tmp_path / "c.urdf"), "world", "flange_calibrated").arm
    q = random_states(arm, 10)
    dp, dR = fk_error(np.asarray(tool_pose(back, q)), np.asarray(tool_pose(arm, q)))
    assert dp < TOL_MM and dR < TOL_R


def test_export_reports_what_a_urdf_cannot_hold(tmp_path, capsys):
    imp = import_urdf(SLIDER, "world", "tool")
    text = imp.to_toml().replace('name = "turn"\n', 'name = "turn"\nmass = 2.5\n')
    text = text.replace("    -9.81,\n", "    -9.80,\n", 1)
    model = tmp_path / "m.toml"
    model.write_text(text)
    exp = export_urdf(model, SLIDER, "world", "tool")
    assert any("mass" in w for w in exp.not_held) and any("gravity" in w for w in exp.not_held)
    assert "not held by a URDF" in exp.text and "mass" in exp.text
    out = tmp_path / "cal.urdf"
    args = ["export", "urdf", "--model", str(model), "--urdf", str(SLIDER)]
    args += ["--base", "world", "--tip", "tool", "--out", str(out)]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "warning: the URDF cannot hold module 'turn': mass" in err
    assert main(args) == 1  # --out exists
    assert "file exists" in capsys.readouterr().err
    assert main([*args, "--force"]) == 0


def test_export_refuses_a_model_of_another_chain():
    other = import_urdf(UR5, "base_link", "ee_link").arm
    with pytest.raises(UrdfFileError, match="same names in the same order"):
        export_urdf(other, PANDA, "panda_link0", "panda_hand_tcp")
    panda = import_urdf(PANDA, "panda_link0", "panda_leftfinger").arm
    mods = list(panda.modules)
    mods[-1] = revolute("panda_finger_joint1", [0, 1, 0])
    bad = type(panda)(frames=panda.frames, modules=tuple(mods), frame_names=panda.frame_names)
    with pytest.raises(UrdfFileError, match="is prismatic"):
        export_urdf(bad, PANDA, "panda_link0", "panda_leftfinger")


# -------------------------------------------------------------------------------- command line


def test_cli_import_and_export(tmp_path, capsys):
    model = tmp_path / "ur5.toml"
    args = ["import", "urdf", str(UR5), "--base", "base_link", "--tip", "ee_link"]
    assert main([*args, "--out", str(model)]) == 0
    assert "6 modules" in capsys.readouterr().out
    assert main([*args, "--out", str(model)]) == 1
    assert "file exists" in capsys.readouterr().err
    table = tmp_path / "dh.csv"
    table.write_text(UR5_DH)
    dh = tmp_path / "dh.toml"
    assert main(["import", "dh", str(table), "--convention", "modified", "--out", str(dh)]) == 0
    assert load_model(dh).module_names[0] == "shoulder_pan"
    out = tmp_path / "cal.urdf"
    cmd = ["export", "urdf", "--model", str(model), "--urdf", str(UR5), "--base", "base_link"]
    assert main([*cmd, "--tip", "ee_link", "--out", str(out)]) == 0
    assert "no joint origin changed" in capsys.readouterr().out
    assert main(["import", "dh", str(table), "--out", str(dh)]) == 2  # --convention required


# --------------------------------------------------------------------------------- bad input

BAD_URDF = [
    ("<robot name='r'><link name='a'/><joint name='j'", "malformed XML"),
    (
        "<robot name='r'><link name='a'/><link name='b'/><joint name='j' type='revolute'>"
        "<parent link='a'/><child link='c'/></joint></robot>",
        "child link 'c' is not a <link>",
    ),
    (
        "<robot name='r'><link name='a'/><link name='b'/><joint name='j' type='revolute'>"
        "<parent link='a'/><child link='b'/></joint></robot>",
        "needs <limit lower",
    ),
    (
        "<robot name='r'><link name='a'/><link name='b'/><joint name='j' type='planar'>"
        "<parent link='a'/><child link='b'/></joint></robot>",
        "a planar joint is in the chain",
    ),
    (
        "<robot name='r'><link name='a'/><link name='b'/><joint name='j' type='fixed'>"
        "<parent link='a'/><child link='b'/></joint></robot>",
        "has no revolute, continuous",
    ),
    (
        "<robot name='r'><link name='a'/><link name='b'/><joint name='j.1' type='continuous'>"
        "<parent link='a'/><child link='b'/></joint></robot>",
        r"<joint name='j.1'>: the joint",
    ),
]


@pytest.mark.parametrize("text,match", BAD_URDF)
def test_bad_urdf(tmp_path, text, match):
    path = tmp_path / "bad.urdf"
    path.write_text(text)
    with pytest.raises(UrdfFileError, match=match) as e:
        import_urdf(path, "a", "b")
    assert str(path) in str(e.value)


def test_bad_chain_links():
    with pytest.raises(UrdfFileError, match="tip link 'nope' is not a <link>"):
        import_urdf(UR5, "base_link", "nope")
    with pytest.raises(UrdfFileError, match="swap --base and --tip"):
        import_urdf(UR5, "ee_link", "base_link")
    with pytest.raises(UrdfFileError, match="not below the base"):
        import_urdf(PANDA, "panda_leftfinger", "panda_rightfinger")
    with pytest.raises(UrdfFileError, match="mimic joint"):
        import_urdf(PANDA, "panda_link0", "panda_rightfinger")
    with pytest.raises(UrdfFileError, match="floating joint"):
        import_urdf(SLIDER, "world", "drone")
    with pytest.raises(OSError):
        import_urdf(DATA / "missing.urdf", "a", "b")


@pytest.mark.parametrize(
    "text,match",
    [
        ("joint,type,a,alpha,d\n", "missing column 'theta'"),
        ("joint,type,a,alpha,d,theta,tilt\n", "line 1: unknown column 'tilt'"),
        ("# c\njoint,type,a,alpha,d,theta\nj1,revolute,0,x,0,0\n", "line 3, column 'alpha'"),
        ("joint,type,a,alpha,d,theta\nj1,screw,0,0,0,0\n", "line 2, column 'type'"),
        ("joint,type,a,alpha,d,theta\nj1,revolute,0,0,0,0\nj1,revolute,0,0,0,0\n", "twice"),
        ("joint,type,a,alpha,d,theta,lower\n", "both 'lower' and 'upper'"),
        ("joint,type,a,alpha,d,theta,lower,upper\nj,revolute,0,0,0,0,1,-1\n", "column 'upper'"),
        ("joint,type,a,alpha,d,theta\nj,revolute,0,0,0\n", "line 2: 5 cells"),
        ("joint,type,a,alpha,d,theta\nj,revolute,0,0,inf,0\n", "column 'd'"),
        ("joint,type,a,alpha,d,theta\n", "no joint rows"),
    ],
)
def test_bad_dh(text, match):
    with pytest.raises(DHFileError, match=match) as e:
        loads_dh(text, source="t.csv")
    assert str(e.value).startswith("t.csv: ")
