"""A station model (nominal or calibrated) written as a URDF.

A model read from a URDF is written as that URDF with the joint origins on its chain updated: every link
keeps its frame on its body (meshes, inertials and everything off the chain stay valid), the zero offsets are
folded into the origins (a URDF has no zero offset: at the controller's reading q the URDF gives the
calibrated pose), and the tool change goes into the last fixed joint before the tip link; when the tip link is
the last joint's own link (its origin must stay on the joint axis) a changed tool is added as the fixed joint
``station_tool_joint`` to a new link ``station_tool``. Any other model is written as a new URDF: ``base_link``, one link
per joint (its frame right after the joint's motion), and the tool as the fixed joint ``tool0_joint`` to the
link ``tool0``; link masses and the payload become ``<inertial>`` point masses.

Gravity compliance has no place in a URDF: the values are written in a comment; the station model file keeps
them."""

from __future__ import annotations

import copy

import numpy as np

from station.kinematics import se3
from station.kinematics.chain import forward
from station.kinematics.model import Model
from station.kinematics.urdfxml import Comment, Node, serialize

TOOL_LINK, TOOL_JOINT = "station_tool", "station_tool_joint"


def _f(x: float) -> str:
    x = round(float(x), 15)
    return "0" if x == 0 else f"{x:.15g}"


def _vec(v) -> str:
    return " ".join(_f(x) for x in v)


def _origin_attrs(T: np.ndarray) -> dict[str, str]:
    return {"xyz": _vec(T[:3, 3]), "rpy": _vec(se3.matrix_to_rpy(T[:3, :3]))}


def _frames_at_zero(model: Model):
    """Tool pose, the frame before every chain element and the frame after each link frame element, at
    q = 0 (undeflected: a URDF has no gravity)."""
    T, prefix = forward(model.chain, np.zeros((1, model.n_joints)), model.params, keep_prefix=True)
    K = model.chain.n_elements
    after = [prefix[0, e + 1] if e + 1 < K else T[0] for e in range(K)]
    return T[0], prefix[0], after


def _compliance_note(model: Model) -> str | None:
    vals = {n: v for n, v in model.param_dict().items() if n.startswith("compliance.") and v}
    if not vals:
        return None
    text = ", ".join(f"{n} = {v:.6g}" for n, v in vals.items())
    return (f" gravity compliance (rad per N m) is not part of URDF; this model has {text}. Keep the station "
            f"model file for it. ")


def urdf_text(model: Model, note: str = "") -> str:
    """The URDF document of ``model`` (see the module doc); ``note`` goes into a leading comment."""
    src = model.source.get("urdf") or {}
    if "chain" in src:
        return _rewrite(model, src, note)
    return _generate(model, note)


def _rewrite(model: Model, src: dict, note: str) -> str:
    ch = src["chain"]
    tool, _, after = _frames_at_zero(model)
    M = [after[e] for e in model.frames]
    W_link = [Mk @ X for Mk, X in zip(M, src["link_in_frame"], strict=True)]
    root = copy.deepcopy(ch.robot.root)
    nodes = {n.attrib.get("name"): n for n in root.elements("joint")}
    last_mov = max(i for i, j in enumerate(ch.path) if j.movable)
    cur = np.eye(4)  # pose of the parent link of the joint at hand, on the new origins
    k = 0
    for i, j in enumerate(ch.path):
        node = nodes[j.name]
        if j.movable:
            child = W_link[k]
            _set_origin(node, se3.invert(cur) @ child)
            axis = child[:3, :3].T @ M[k][:3, 2]  # the joint's axis (MDH z) in its child link
            _set_child(node, "axis", {"xyz": _vec(axis / np.linalg.norm(axis))})
            cur, k = child, k + 1
        elif i == len(ch.path) - 1 and i > last_mov:  # the last fixed joint before the tip carries the tool
            _set_origin(node, se3.invert(cur) @ tool)
            cur = tool
        else:
            cur = cur @ j.origin
    extra = se3.invert(cur) @ tool
    if ch.path[-1].movable and np.abs(extra - np.eye(4)).max() > 1e-12:
        # the tip is the last joint's own link, whose origin must stay on the joint axis: the tool gets its own
        root.children += [Node("link", {"name": TOOL_LINK}, 0), "\n",
                          Node("joint", {"name": TOOL_JOINT, "type": "fixed"}, 0,
                               [Node("parent", {"link": ch.tip}, 0), Node("child", {"link": TOOL_LINK}, 0),
                                Node("origin", _origin_attrs(extra), 0)]), "\n"]
    text = [f" {model.name}: written by station from a URDF ({src.get('path')}), chain {ch.base} -> {ch.tip}; "
            f"joint origins on the chain hold the model's values (zero offsets folded in). {note}"]
    cn = _compliance_note(model)
    root.children[:0] = [Comment(t) for t in text + ([cn] if cn else [])] + ["\n"]
    return serialize(root)


def _set_child(node: Node, tag: str, attrs: dict[str, str]) -> None:
    el = node.first(tag)
    if el is None:
        el = Node(tag, {}, node.line)
        node.children.append(el)
    el.attrib.update(attrs)


def _set_origin(node: Node, T: np.ndarray) -> None:
    _set_child(node, "origin", _origin_attrs(T))


def _inertial(mass: float, com) -> list[str]:
    return ["    <inertial>", f'      <origin xyz="{_vec(com)}" rpy="0 0 0"/>', f'      <mass value="{_f(mass)}"/>',
            '      <inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/>  <!-- point mass -->',
            "    </inertial>"]


def _generate(model: Model, note: str) -> str:
    tool, prefix, after = _frames_at_zero(model)
    ch = model.chain
    n = model.n_joints
    elem = [int(np.flatnonzero(ch.joint == i)[0]) for i in range(n)]
    L = [np.eye(4)] + [after[e] for e in elem]  # link k's frame: right after joint k's motion at q = 0
    lines = ['<?xml version="1.0"?>',
             f"<!-- {model.name}: written by station from a {model.convention.upper()} model. Lengths in m, "
             f"angles in rad. {note} -->"]
    cn = _compliance_note(model)
    if cn:
        lines.append(f"<!--{cn}-->")
    lines += [f'<robot name="{model.name}">', '  <link name="base_link"/>']
    link_names = ["base_link"] + [f"link{k + 1}" for k in range(n)]
    load = model.load
    for k, jt in enumerate(model.joints):
        lines.append(f'  <link name="{link_names[k + 1]}">')
        if load is not None:
            m, com = load.link_mass(k + 1)
            if m > 0:  # com is in the station link frame; the URDF link frame sits right after the joint
                F = after[model.frames[k]]
                lines += _inertial(m, (se3.invert(L[k + 1]) @ F @ np.append(com, 1.0))[:3])
        lines.append("  </link>")
        axis = np.zeros(3)
        axis[int(ch.axis[elem[k]]) % 3] = 1.0
        kind = "revolute" if jt.revolute else "prismatic"
        lo, hi = jt.lower, jt.upper
        lines += [f'  <joint name="{jt.name}" type="{kind}">', f'    <parent link="{link_names[k]}"/>',
                  f'    <child link="{link_names[k + 1]}"/>',
                  '    <origin xyz="{xyz}" rpy="{rpy}"/>'.format(**_origin_attrs(se3.invert(L[k]) @ L[k + 1])),
                  f'    <axis xyz="{_vec(axis)}"/>',
                  f'    <limit lower="{_f(lo)}" upper="{_f(hi)}" velocity="{_f(jt.max_velocity)}" effort="0"/>',
                  "  </joint>"]
    lines.append('  <link name="tool0">')
    if load is not None and load.payload[0] > 0:
        lines += _inertial(*load.payload)
    lines.append("  </link>")
    lines += ['  <joint name="tool0_joint" type="fixed">', f'    <parent link="{link_names[n]}"/>',
              '    <child link="tool0"/>',
              '    <origin xyz="{xyz}" rpy="{rpy}"/>'.format(**_origin_attrs(se3.invert(L[n]) @ tool)),
              "  </joint>", "</robot>", ""]
    return "\n".join(lines)


__all__ = ["urdf_text"]
