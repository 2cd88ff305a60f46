"""URDF files: the serial chain between two links as an :class:`~cdra_jax.arm.Arm`, and back.

Reading uses `yourdfpy <https://github.com/clemense/yourdfpy>`_ (no meshes are loaded, no scene
graph is built). The chain from ``base`` to ``tip`` is the path of joints from the base link down
the kinematic tree to the tip link. Its revolute, continuous and prismatic joints become the
modules (named exactly as the joints, in chain order); fixed joints are folded into the fixed
frames between them::

    T_base_tip(q) = F_0 M_1(q_1) F_1 ... M_K(q_K) F_K

* ``F_0``: the base link to the first movable joint's frame (the fixed joints' origins on the
  way, then the first movable joint's ``<origin>``), named after the base link;
* ``F_i``: joint i's child link frame to joint i+1's frame, named after joint i's child link;
* ``F_K``: the last movable joint's child link frame to the tip link, named after the tip link.

Frame names keep the link names where they are valid and unique (characters other than letters,
digits, ``_`` and ``-`` become ``_``; a clash with a joint name or another frame gets a suffix).
Units: lengths in mm (URDF is in metres), angles in rad; a prismatic joint value and its limits
in mm. Module ``axis`` is the joint's ``<axis>`` (in the joint frame, which is the module frame);
limits are the joint's ``<limit lower upper>``; a continuous joint gets ``[-pi, pi]``.

Writing (:func:`apply_arm_to_urdf`, :func:`urdf_text`) puts a model's fixed frames back into the
chain's joint origins: in each segment between two movable joints, the fixed joints keep their
origins and the joint that ends the segment (the next movable joint, or for ``F_K`` the fixed
joint reaching the tip) carries the rest, so that the URDF's forward kinematics equals the
model's. Everything else of the file is kept (elements yourdfpy does not model, such as
``<transmission>`` and ``<gazebo>``, are copied from the original); what a URDF cannot hold is
listed by :func:`not_held`.
"""

from __future__ import annotations

import copy
import io
import logging
import math
import os
import re
from collections import Counter
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..arm import Arm, Module
from ..compilation import device_array
from .model import RESERVED_MODULE_NAMES, arm_to_dict

MOVABLE_TYPES = ("revolute", "continuous", "prismatic")
"""URDF joint types that become modules."""
M_TO_MM = 1000.0
_NAME_FORBIDDEN = frozenset('.,"')  # as io.model: module names make measurement column names
_DEFAULT_GRAVITY = (0.0, 0.0, -9.81)
_TOL = 1e-12


class UrdfFileError(ValueError):
    """A URDF file is malformed or has no usable chain; the message names the file and element."""


def _keep_filename(fname: str) -> str:
    """yourdfpy filename handler: keep mesh file names as written (``package://...``)."""
    return fname


class _Capture(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@contextmanager
def _yourdfpy_errors() -> Iterator[_Capture]:
    """Collect the errors yourdfpy logs (it logs a malformed XML file, then parses it in a
    forgiving mode) so that they become :class:`UrdfFileError` instead of a partial model."""
    logger = logging.getLogger("yourdfpy")
    handler = _Capture()
    logger.addHandler(handler)
    propagate = logger.propagate
    logger.propagate = False
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def read_urdf(source: str | os.PathLike | bytes, label: str | None = None) -> Any:
    """Load a URDF file (path) or text (bytes) with yourdfpy, without meshes or scene graph.

    Returns a ``yourdfpy.URDF``. Raises :class:`UrdfFileError` naming the file (``label``) for
    malformed XML or a file yourdfpy cannot read, ``OSError`` when the file cannot be read.
    """
    import yourdfpy

    if isinstance(source, bytes):
        label = label or "<urdf>"
        fobj: Any = io.BytesIO(source)
    else:
        label = label or str(source)
        data = Path(source).read_bytes()  # OSError (missing file, folder) with the path
        fobj = io.BytesIO(data)
    with _yourdfpy_errors() as log:
        try:
            urdf = yourdfpy.URDF.load(
                fobj,
                load_meshes=False,
                build_scene_graph=False,
                load_collision_meshes=False,
                build_collision_scene_graph=False,
                filename_handler=_keep_filename,
            )
        except Exception as e:  # yourdfpy raises what the XML gives it (KeyError, TypeError...)
            if log.messages:
                raise UrdfFileError(f"{label}: malformed XML: {log.messages[0]}") from None
            detail = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
            raise UrdfFileError(f"{label}: not a readable URDF file: {detail}") from None
    if log.messages:
        raise UrdfFileError(f"{label}: malformed XML: {log.messages[0]}")
    _check_tree(urdf, label)
    return urdf


def _jwhere(joint: Any) -> str:
    return f"<joint name={joint.name!r}>"


def _check_tree(urdf: Any, source: str) -> None:
    """Every joint names existing links, names are unique, and each link has one parent."""
    robot = urdf.robot
    links = [link.name for link in robot.links]
    dup = sorted({n for n in links if links.count(n) > 1})
    if dup:
        raise UrdfFileError(f"{source}: <link name={dup[0]!r}> appears more than once")
    names = [j.name for j in robot.joints]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UrdfFileError(f"{source}: <joint name={dup[0]!r}> appears more than once")
    known = set(links)
    parent_of: dict[str, str] = {}
    for j in robot.joints:
        for role, link in (("parent", j.parent), ("child", j.child)):
            if link not in known:
                raise UrdfFileError(
                    f"{source}: {_jwhere(j)}: {role} link {link!r} is not a <link> of the file"
                )
        if j.child in parent_of:
            raise UrdfFileError(
                f"{source}: {_jwhere(j)}: link {j.child!r} is already the child of "
                f"<joint name={parent_of[j.child]!r}>; a URDF is a tree (one parent per link)"
            )
        parent_of[j.child] = j.name


def chain_joints(urdf: Any, base: str, tip: str, source: str) -> list[Any]:
    """The joints (yourdfpy ``Joint`` objects) from link ``base`` down to link ``tip``, in order.

    Raises :class:`UrdfFileError` for an unknown link, ``base == tip`` or no chain (the tip is
    not below the base in the tree).
    """
    robot = urdf.robot
    links = [link.name for link in robot.links]
    for flag, link in (("base", base), ("tip", tip)):
        if link not in links:
            near = [n for n in links if n.lower() == link.lower()]
            hint = f" (did you mean {near[0]!r}?)" if near else f"; links: {', '.join(links)}"
            raise UrdfFileError(f"{source}: {flag} link {link!r} is not a <link> of the file{hint}")
    if base == tip:
        raise UrdfFileError(f"{source}: base and tip are the same link {base!r}; no chain")
    parent_joint = {j.child: j for j in robot.joints}

    def up(link: str) -> list[Any]:
        path = []
        while link in parent_joint:
            j = parent_joint[link]
            path.append(j)
            link = j.parent
        return path

    path: list[Any] = []
    link = tip
    while link != base:
        if link not in parent_joint:
            if tip in {j.parent for j in up(base)}:
                raise UrdfFileError(
                    f"{source}: no chain from base {base!r} to tip {tip!r}: the tip is above the "
                    "base in the tree (swap --base and --tip)"
                )
            raise UrdfFileError(
                f"{source}: no chain from base {base!r} to tip {tip!r}: the tip link is not "
                f"below the base link (the tree's path from {tip!r} up reaches the root "
                f"{link!r} without passing {base!r})"
            )
        j = parent_joint[link]
        path.append(j)
        link = j.parent
    return path[::-1]


def _origin(joint: Any) -> np.ndarray:
    """Joint origin ``(4, 4)`` with the translation in mm."""
    T = np.eye(4) if joint.origin is None else np.array(joint.origin, dtype=float)
    T[:3, 3] *= M_TO_MM
    return T


def _frame_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_\-]", "_", name) or "frame"


def _unique(names: Sequence[str], taken: set[str]) -> list[str]:
    out = []
    for n in names:
        cand, k = n, 2
        if cand in taken:
            cand = f"{n}_frame"
        while cand in taken:
            cand, k = f"{n}_frame{k}", k + 1
        taken.add(cand)
        out.append(cand)
    return out


def _check_module_name(joint: Any, source: str) -> None:
    name = joint.name
    bad = sorted({ch for ch in name if ch in _NAME_FORBIDDEN or not ch.isprintable()})
    if bad or name != name.strip() or not name or name in RESERVED_MODULE_NAMES:
        why = (
            f"contains {' or '.join(map(repr, bad))}"
            if bad
            else "is reserved by the measurement file"
            if name in RESERVED_MODULE_NAMES
            else "starts or ends with a space or is empty"
        )
        raise UrdfFileError(
            f"{source}: {_jwhere(joint)}: the joint name {why}; a module is named exactly as its "
            "joint and the name makes measurement-file columns (<module>.q), so rename the joint"
        )


def _axis(joint: Any, source: str) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if joint.axis is None else np.asarray(joint.axis, dtype=float)
    n = np.linalg.norm(a) if a.shape == (3,) else 0.0
    if a.shape != (3,) or not np.all(np.isfinite(a)) or n < 1e-12:
        raise UrdfFileError(f"{source}: {_jwhere(joint)}: <axis xyz> must be a non-zero 3-vector")
    return a / n


def _limits(joint: Any, source: str) -> tuple[float, float]:
    if joint.type == "continuous":
        return (-math.pi, math.pi)
    lim = joint.limit
    lo = None if lim is None else lim.lower
    hi = None if lim is None else lim.upper
    if lo is None or hi is None or not (np.isfinite(lo) and np.isfinite(hi)) or not lo < hi:
        raise UrdfFileError(
            f"{source}: {_jwhere(joint)}: a {joint.type} joint needs <limit lower=... upper=...> "
            f"with lower < upper, got lower={lo!r} upper={hi!r}"
        )
    scale = M_TO_MM if joint.type == "prismatic" else 1.0
    return (float(lo) * scale, float(hi) * scale)


def _check_joint(joint: Any, source: str) -> None:
    if joint.type in ("floating", "planar"):
        raise UrdfFileError(
            f"{source}: {_jwhere(joint)}: a {joint.type} joint is in the chain; a model's modules "
            "are revolute or prismatic (choose base and tip links around it)"
        )
    if joint.type not in (*MOVABLE_TYPES, "fixed"):
        raise UrdfFileError(f"{source}: {_jwhere(joint)}: unknown joint type {joint.type!r}")
    if joint.mimic is not None and joint.type != "fixed":
        raise UrdfFileError(
            f"{source}: {_jwhere(joint)}: a mimic joint (it follows <joint "
            f"name={joint.mimic.joint!r}>) is in the chain; a model's modules move independently "
            "and a coupled joint has no module kind, so choose a tip before it"
        )


@dataclass(frozen=True)
class UrdfChain:
    """The chain of a URDF between two links, as a model.

    Attributes:
        arm: the model (frames in mm, modules named as the joints).
        joints: names of every joint of the chain, base to tip (fixed ones included).
        movable: names of the movable joints (the modules), in chain order.
        joint_types: URDF type of each movable joint (``continuous`` kept apart from revolute).
        links: the link names base to tip.
        base, tip: the links the chain runs between.
    """

    arm: Arm
    joints: tuple[str, ...]
    movable: tuple[str, ...]
    joint_types: tuple[str, ...]
    links: tuple[str, ...]
    base: str
    tip: str


def segments(joints: Sequence[Any]) -> list[list[Any]]:
    """Split the chain's joints into the K+1 segments of the fixed frames: segment i (< K) ends
    with movable joint i+1 (its origin included), the last holds the fixed joints to the tip."""
    out: list[list[Any]] = [[]]
    for j in joints:
        out[-1].append(j)
        if j.type in MOVABLE_TYPES:
            out.append([])
    return out


def chain_arm(urdf: Any, base: str, tip: str, source: str, name: str | None = None) -> UrdfChain:
    """The model of the chain from link ``base`` to link ``tip`` of a loaded URDF.

    The model's tool pose ``tool_pose(arm, q)`` (q in the chain's movable-joint order, rad or
    mm) equals the pose of the tip link in the base link frame, translation in mm.
    """
    joints = chain_joints(urdf, base, tip, source)
    for j in joints:
        _check_joint(j, source)
    movable = [j for j in joints if j.type in MOVABLE_TYPES]
    if not movable:
        raise UrdfFileError(
            f"{source}: the chain from {base!r} to {tip!r} has no revolute, continuous or "
            f"prismatic joint (only fixed joints: {', '.join(j.name for j in joints)})"
        )
    modules = []
    for j in movable:
        _check_module_name(j, source)
        modules.append(
            Module(
                name=j.name,
                kind="prismatic" if j.type == "prismatic" else "revolute",
                axis=device_array(_axis(j, source)),
                limits=(_limits(j, source),),
            )
        )
    frames = []
    for seg in segments(joints):
        T = np.eye(4)
        for j in seg:
            T = T @ _origin(j)
        frames.append(T)
    raw_names = [base, *(j.child for j in movable[:-1]), tip]
    frame_names = _unique([_frame_name(n) for n in raw_names], {j.name for j in movable})
    arm = Arm(
        frames=device_array(np.stack(frames)),
        modules=tuple(modules),
        frame_names=tuple(frame_names),
        name=str(name or urdf.robot.name or "robot"),
        description=f"imported from URDF {Path(source).name}: chain {base} -> {tip}",
    )
    return UrdfChain(
        arm=arm,
        joints=tuple(j.name for j in joints),
        movable=tuple(j.name for j in movable),
        joint_types=tuple(j.type for j in movable),
        links=(base, *(j.child for j in joints)),
        base=base,
        tip=tip,
    )


def load_urdf_chain(
    path: str | os.PathLike, base: str, tip: str, name: str | None = None
) -> UrdfChain:
    """Read a URDF file and return the model of its chain from ``base`` to ``tip``."""
    urdf = read_urdf(path)
    return chain_arm(urdf, base, tip, str(path), name)


# --------------------------------------------------------------------------------------------
# Export


def not_held(arm: Arm) -> list[str]:
    """What of the model a URDF cannot hold (one line each): cables, masses, cable properties,
    a non-default gravity, markers, effects and any other model content beyond frames, joint
    axes and limits."""
    d = arm_to_dict(arm)
    out = []
    for key in sorted(set(d) - {"name", "description", "gravity", "frames", "modules", "effects"}):
        out.append(f"the model's [[{key}]] (a URDF has no place for them)")
    for e in arm.effects:
        values = ", ".join(f"{n} = {v:.6g} {u}" for n, v, u in e.parameters)
        out.append(
            f"the model's effect {e.label} ({values}): a URDF holds the geometric chain only, "
            "so predictions from the exported file lack this physics; keep the model TOML "
            "for them"
        )
    g = np.asarray(d.get("gravity", _DEFAULT_GRAVITY), dtype=float)
    if not np.allclose(g, _DEFAULT_GRAVITY, rtol=0, atol=1e-12):
        out.append(f"gravity {g.tolist()} m/s^2 (a URDF has no gravity)")
    for m in d["modules"]:
        extra = sorted(set(m) - {"name", "kind", "axis", "limits"})
        if extra:
            out.append(f"module {m['name']!r}: {', '.join(extra)} (no URDF element for them)")
    return out


def _to_metres(F: np.ndarray) -> np.ndarray:
    T = np.array(F, dtype=float)
    T[:3, 3] /= M_TO_MM
    return T


def apply_arm_to_urdf(urdf: Any, arm: Arm, base: str, tip: str, source: str) -> list[str]:
    """Write ``arm``'s fixed frames (and changed axes and limits) into the chain's joints of the
    loaded URDF ``urdf`` (modified in place); returns notes on what changed or was added.

    The model's modules must be the chain's movable joints (same names, order and kinds). In
    each segment the last joint's origin becomes ``inv(prefix) F_i`` (``prefix``: the product of
    the segment's other, unchanged, fixed-joint origins). When no joint leads from the last
    movable joint's child link to the tip (the tip *is* that link) and ``F_K`` is not the
    identity, a fixed joint ``<tip>_calibrated_joint`` and a link ``<tip>_calibrated`` are added.
    """
    import yourdfpy

    joints = chain_joints(urdf, base, tip, source)
    for j in joints:
        _check_joint(j, source)
    movable = [j for j in joints if j.type in MOVABLE_TYPES]
    mods = arm.modules
    if [j.name for j in movable] != [m.name for m in mods]:
        raise UrdfFileError(
            f"{source}: the chain {base!r} -> {tip!r} has movable joints "
            f"{[j.name for j in movable]}, the model has modules {[m.name for m in mods]}; "
            "export needs the same names in the same order (export the chain the model was "
            "imported from)"
        )
    for j, m in zip(movable, mods, strict=True):
        kind = "prismatic" if j.type == "prismatic" else "revolute"
        if m.kind != kind:
            raise UrdfFileError(
                f"{source}: {_jwhere(j)} is {j.type}, the model's module {m.name!r} is {m.kind}"
            )
    frames = np.asarray(arm.frames, dtype=float)
    notes: list[str] = []
    segs = segments(joints)
    for i, seg in enumerate(segs):
        F = frames[i]
        if not seg:
            if np.max(np.abs(F - np.eye(4))) > _TOL:
                link, joint = f"{tip}_calibrated", f"{tip}_calibrated_joint"
                taken_l = {lk.name for lk in urdf.robot.links}
                taken_j = {jt.name for jt in urdf.robot.joints}
                if link in taken_l or joint in taken_j:
                    raise UrdfFileError(
                        f"{source}: the calibrated tool frame {arm.frame_names[i]!r} needs a new "
                        f"link {link!r}, which the file already has"
                    )
                urdf.robot.links.append(yourdfpy.Link(name=link))
                urdf.robot.joints.append(
                    yourdfpy.Joint(
                        name=joint, type="fixed", parent=tip, child=link, origin=_to_metres(F)
                    )
                )
                notes.append(
                    f"added fixed joint {joint!r} and link {link!r}: the calibrated tool frame "
                    f"{arm.frame_names[i]!r} is not the identity but no joint leads to the tip "
                    f"{tip!r}; use {link!r} as the tool link"
                )
            continue
        prefix = np.eye(4)
        for j in seg[:-1]:
            prefix = prefix @ _origin(j)
        new = _to_metres(np.linalg.inv(prefix) @ F)
        last = seg[-1]
        old = np.eye(4) if last.origin is None else np.asarray(last.origin, dtype=float)
        last.origin = new
        dp = np.linalg.norm((new[:3, 3] - old[:3, 3]) * M_TO_MM)
        dR = np.linalg.norm(new[:3, :3] - old[:3, :3])
        if dp > _TOL or dR > _TOL:
            notes.append(
                f"{_jwhere(last)} origin carries frame {arm.frame_names[i]!r} (moved {dp:.4g} mm)"
            )
    for j, m in zip(movable, mods, strict=True):
        axis = np.asarray(m.axis, dtype=float)
        if np.max(np.abs(axis - _axis(j, source))) > _TOL:
            j.axis = axis
            notes.append(f"{_jwhere(j)} axis set to the model's {axis.tolist()}")
        lo, hi = m.limits[0]
        if j.type == "continuous":
            if abs(lo + math.pi) > _TOL or abs(hi - math.pi) > _TOL:
                notes.append(
                    f"{_jwhere(j)} is continuous (no limits in a URDF): model limits "
                    f"[{lo}, {hi}] not written"
                )
            continue
        old_lim = _limits(j, source)
        if abs(old_lim[0] - lo) > _TOL or abs(old_lim[1] - hi) > _TOL:
            scale = M_TO_MM if j.type == "prismatic" else 1.0
            j.limit.lower, j.limit.upper = lo / scale, hi / scale
            notes.append(f"{_jwhere(j)} limits set to the model's [{lo}, {hi}]")
    return notes


def _paths(root: Any) -> Counter:
    """Multiset of element paths (``robot/joint/origin``) of an lxml tree, comments left out."""
    out: Counter = Counter()

    def walk(el: Any, prefix: str) -> None:
        if not isinstance(el.tag, str):
            return
        p = f"{prefix}/{el.tag}" if prefix else el.tag
        out[p] += 1
        for c in el:
            walk(c, p)

    walk(root, "")
    return out


def urdf_text(urdf: Any, original: bytes, comment: Sequence[str] = ()) -> tuple[str, list[str]]:
    """The URDF XML text of ``urdf`` (written by yourdfpy) and what of ``original`` it lost.

    Top-level elements yourdfpy does not model (``<transmission>``, ``<gazebo>``, ...) and the
    sub-elements of links and joints it does not write (``<mimic>``, ``<calibration>``,
    ``<safety_controller>``, ...) are copied from the original file; the lines of ``comment``
    become an XML comment at the top of ``<robot>``. Returns ``(text, lost)``: ``lost`` names
    each element path of the original that the text still lacks (with counts), and notes
    dropped XML comments.
    """
    from lxml import etree

    tree = urdf.write_xml()
    root = tree.getroot()
    orig = etree.parse(io.BytesIO(original), etree.XMLParser(remove_blank_text=True)).getroot()
    written_by_name = {(el.tag, el.get("name")): el for el in root if isinstance(el.tag, str)}
    for el in orig:
        if not isinstance(el.tag, str):
            continue
        if el.tag not in ("link", "joint", "material"):
            root.append(copy.deepcopy(el))
            continue
        # Sub-elements yourdfpy reads but does not write (<mimic>, <calibration>,
        # <safety_controller> of joints) or does not read at all: copied from the original.
        out = written_by_name.get((el.tag, el.get("name")))
        if out is not None:
            have = {c.tag for c in out if isinstance(c.tag, str)}
            for c in el:
                if isinstance(c.tag, str) and c.tag not in have:
                    out.append(copy.deepcopy(c))
    if comment:
        body = "\n".join(f"  {c}" for c in comment).replace("--", "- -")
        root.insert(0, etree.Comment(f"\n{body}\n"))
    etree.indent(root, space="  ")
    text = etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True)
    written = _paths(root)
    lost = [
        f"<{p}> x{n - written.get(p, 0)}"
        for p, n in sorted(_paths(orig).items())
        if n > written.get(p, 0)
    ]
    n_comments = sum(1 for el in orig.iter() if isinstance(el, etree._Comment))
    before = orig.getroottree().getroot().itersiblings(preceding=True)
    n_comments += sum(1 for el in before if isinstance(el, etree._Comment))
    if n_comments:
        lost.append(f"{n_comments} XML comment(s) of the original file")
    return text.decode("utf-8"), lost
