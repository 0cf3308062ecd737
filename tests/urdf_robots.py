"""URDF robots the tests write: a UR5e from its published DH table, a 7-DOF arm with an offset elbow and a
rotated hand (ball tool off the flange axis, mimic fingers off the chain), and a rail + SCARA with prismatic
axes. Plain text, written the way robot vendors write them (joint origins with rpy, fixed frames)."""

from __future__ import annotations

import math

import numpy as np

# Universal Robots' published UR5e DH table (a, d, alpha) and link masses / centres of mass (DH frame i)
UR5E_DH = [(0.0, 0.1625, math.pi / 2), (-0.425, 0.0, 0.0), (-0.3922, 0.0, 0.0), (0.0, 0.1333, math.pi / 2),
           (0.0, 0.0997, -math.pi / 2), (0.0, 0.0996, 0.0)]
UR5E_MASS = [(3.761, (0, -0.02561, 0.00193)), (8.058, (0.2125, 0, 0.11336)), (2.846, (0.15, 0, 0.0265)),
             (1.37, (0, -0.0018, 0.01634)), (1.3, (0, 0.0018, 0.01634)), (0.365, (0, 0, -0.001159))]
UR5E_TOOL = ((0.01, -0.02, 0.15), (0.3, -0.2, 0.1))  # tool0 in the flange: xyz, rpy


def _inertial(mass: float, com) -> str:
    return (f'<inertial><origin xyz="{com[0]} {com[1]} {com[2]}" rpy="0.1 0.2 0.3"/><mass value="{mass}"/>'
            f'<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>')


def _box(name: str) -> str:
    return f'<visual><geometry><box size="0.05 0.05 0.05"/></geometry></visual><!-- {name} -->'


def ur5e_urdf(masses: bool = True) -> str:
    """Link i's frame is DH frame i-1 turned by joint i; the DH transform Tz(d) Tx(a) Rx(alpha) is the next
    joint's origin. A REP-103 'base' frame and the inertia frame hang off base_link (fixed), as in the
    vendor's description; masses are given in DH frame i, i.e. in the next joint's origin."""
    s = ['<?xml version="1.0"?>', '<robot name="ur5e_urdf">', '  <link name="base_link"/>',
         '  <link name="base"/>',
         '  <joint name="base_link-base_fixed_joint" type="fixed"><parent link="base_link"/><child link="base"/>'
         '<origin xyz="0 0 0" rpy="0 0 3.141592653589793"/></joint>']
    prev, xyz, rpy = "base_link", "0 0 0", "0 0 0"
    for i, (a, d, alpha) in enumerate(UR5E_DH):
        inert = ""
        if masses:
            m, c = UR5E_MASS[i]
            # the mass table is in DH frame i = this link's frame moved by Tz(d) Tx(a) Rx(alpha)
            ca, sa = math.cos(alpha), math.sin(alpha)
            p = np.array([a, 0, d]) + np.array([c[0], ca * c[1] - sa * c[2], sa * c[1] + ca * c[2]])
            inert = _inertial(m, p)
        s.append(f'  <link name="link{i + 1}">{inert}{_box(f"link{i + 1}")}</link>')
        s.append(f'  <joint name="joint{i + 1}" type="revolute"><parent link="{prev}"/><child link="link{i + 1}"/>'
                 f'<origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="0 0 1"/>'
                 f'<limit lower="-6.283185307179586" upper="6.283185307179586" effort="150" velocity="3.14"/>'
                 f'<calibration rising="0.0{i}"/></joint>')
        prev, xyz, rpy = f"link{i + 1}", f"{a} 0 {d}", f"{alpha} 0 0"
    (tx, ty, tz), (rr, rp, ry) = UR5E_TOOL
    s += ['  <link name="flange"/>',
          f'  <joint name="flange_fixed" type="fixed"><parent link="{prev}"/><child link="flange"/>'
          f'<origin xyz="{xyz}" rpy="{rpy}"/></joint>',
          '  <link name="tool0"/>',
          f'  <joint name="tool0_fixed" type="fixed"><parent link="flange"/><child link="tool0"/>'
          f'<origin xyz="{tx} {ty} {tz}" rpy="{rr} {rp} {ry}"/></joint>', "</robot>", ""]
    return "\n".join(s)


# 7-DOF arm: (origin xyz, origin rpy, axis) per joint; elbow offset 82.5 mm; masses per link (kg, com)
ARM7 = [((0, 0, 0.333), (0, 0, 0), (0, 0, 1)),
        ((0, 0, 0), (-math.pi / 2, 0, 0), (0, 0, 1)),
        ((0, -0.316, 0), (math.pi / 2, 0, 0), (0, 0, 1)),
        ((0.0825, 0, 0), (math.pi / 2, 0, 0), (0, 0, 1)),
        ((-0.0825, 0.384, 0), (-math.pi / 2, 0, 0), (0, 0, 1)),
        ((0, 0, 0), (math.pi / 2, 0, 0), (0, 0, -1)),
        ((0.088, 0, 0), (math.pi / 2, 0, 0), (0, 0, 1))]
ARM7_MASS = [(4.97, (0.0039, 0.0021, -0.0475)), (0.646, (-0.0031, -0.0287, 0.0035)),
             (3.228, (0.0275, 0.0393, -0.0665)), (3.587, (-0.0532, 0.1047, 0.0274)),
             (1.226, (-0.0117, 0.0427, -0.1086)), (1.666, (0.0601, -0.0141, -0.0104)),
             (0.735, (0.0105, -0.0043, 0.0617))]
ARM7_LIMITS = [(-2.8973, 2.8973), (-1.7628, 1.7628), (-2.8973, 2.8973), (-3.0718, -0.0698), (-2.8973, 2.8973),
               (-0.0175, 3.7525), (-2.8973, 2.8973)]


def arm7_urdf(masses: bool = True, mimic_on_chain: bool = False) -> str:
    """A 7-DOF arm: flange 107 mm after joint 7, a hand turned -45 deg about the flange axis, a ball tool
    30 mm beyond the hand's tip and off its axis, and two fingers (prismatic, the second a mimic of the
    first) that make the chain end ambiguous."""
    s = ['<?xml version="1.0" encoding="utf-8"?>', "<!-- a 7-DOF research arm -->", '<robot name="arm7">',
         '  <link name="world"/>', '  <link name="arm_link0">' + (_inertial(2.9, (-0.025, 0, 0.07)) if masses
                                                                  else "") + "</link>",
         '  <joint name="world_fixed" type="fixed"><parent link="world"/><child link="arm_link0"/>'
         '<origin xyz="0 0 0" rpy="0 0 0"/></joint>']
    for i, ((x, y, z), (r, p, yw), (ax, ay, az)) in enumerate(ARM7):
        inert = _inertial(*ARM7_MASS[i]) if masses else ""
        lo, hi = ARM7_LIMITS[i]
        mimic = '<mimic joint="arm_joint1" multiplier="1"/>' if mimic_on_chain and i == 3 else ""
        s.append(f'  <link name="arm_link{i + 1}">{inert}</link>')
        s.append(f'  <joint name="arm_joint{i + 1}" type="revolute"><parent link="arm_link{i}"/>'
                 f'<child link="arm_link{i + 1}"/><origin xyz="{x} {y} {z}" rpy="{r} {p} {yw}"/>'
                 f'<axis xyz="{ax} {ay} {az}"/><limit lower="{lo}" upper="{hi}" effort="87" velocity="2.175"/>'
                 f'<safety_controller soft_lower_limit="{lo + 0.01}" soft_upper_limit="{hi - 0.01}" '
                 f'k_position="100" k_velocity="40"/>{mimic}</joint>')
    s += ['  <link name="arm_link8"/>',
          '  <joint name="arm_joint8" type="fixed"><parent link="arm_link7"/><child link="arm_link8"/>'
          '<origin xyz="0 0 0.107" rpy="0 0 0"/></joint>',
          '  <link name="hand">' + (_inertial(0.73, (-0.01, 0, 0.03)) if masses else "") + "</link>",
          '  <joint name="hand_joint" type="fixed"><parent link="arm_link8"/><child link="hand"/>'
          '<origin xyz="0 0 0" rpy="0 0 -0.7853981633974483"/></joint>',
          '  <link name="hand_tcp"/>',
          '  <joint name="hand_tcp_joint" type="fixed"><parent link="hand"/><child link="hand_tcp"/>'
          '<origin xyz="0 0 0.1034" rpy="0 0 0"/></joint>',
          '  <link name="ball">' + (_inertial(0.05, (0, 0, 0)) if masses else "") + "</link>",
          '  <joint name="ball_joint" type="fixed"><parent link="hand_tcp"/><child link="ball"/>'
          '<origin xyz="0.004 -0.002 0.03" rpy="0 0 0"/></joint>',
          '  <link name="finger_left">' + (_inertial(0.015, (0, 0.01, 0.02)) if masses else "") + "</link>",
          '  <link name="finger_right">' + (_inertial(0.015, (0, -0.01, 0.02)) if masses else "") + "</link>",
          '  <joint name="finger_joint1" type="prismatic"><parent link="hand"/><child link="finger_left"/>'
          '<origin xyz="0 0 0.0584" rpy="0 0 0"/><axis xyz="0 1 0"/>'
          '<limit effort="100" lower="0.0" upper="0.04" velocity="0.2"/></joint>',
          '  <joint name="finger_joint2" type="prismatic"><parent link="hand"/><child link="finger_right"/>'
          '<origin xyz="0 0 0.0584" rpy="0 0 0"/><axis xyz="0 -1 0"/>'
          '<limit effort="100" lower="0.0" upper="0.04" velocity="0.2"/><mimic joint="finger_joint1"/></joint>',
          "</robot>", ""]
    return "\n".join(s)


def rail_scara_urdf() -> str:
    """A linear rail (prismatic along a tilted x), a SCARA on it: two parallel revolute axes, a prismatic
    quill along -z, a continuous wrist; the tool 40 mm off the wrist axis."""
    return """<?xml version="1.0"?>
<robot name="rail_scara">
  <link name="floor"/>
  <link name="carriage"><inertial><origin xyz="0 0 0.05"/><mass value="12"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <joint name="rail" type="prismatic"><parent link="floor"/><child link="carriage"/>
    <origin xyz="0.1 -0.2 0.05" rpy="0 0.01 0.02"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="1.5" effort="500" velocity="0.5"/></joint>
  <link name="column"/>
  <joint name="column_fixed" type="fixed"><parent link="carriage"/><child link="column"/>
    <origin xyz="0 0 0.4" rpy="0 0 0"/></joint>
  <link name="arm1"><inertial><origin xyz="0.15 0 0"/><mass value="4"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <joint name="shoulder" type="revolute"><parent link="column"/><child link="arm1"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2.5" upper="2.5" effort="50" velocity="3"/></joint>
  <link name="arm2"><inertial><origin xyz="0.12 0 0"/><mass value="3"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <joint name="elbow" type="revolute"><parent link="arm1"/><child link="arm2"/>
    <origin xyz="0.325 0 0.0" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2.6" upper="2.6" effort="50" velocity="3"/></joint>
  <link name="quill"/>
  <joint name="quill" type="prismatic"><parent link="arm2"/><child link="quill"/>
    <origin xyz="0.275 0 0" rpy="0 0 0"/><axis xyz="0 0 -1"/>
    <limit lower="0" upper="0.2" effort="200" velocity="1"/></joint>
  <link name="wrist"/>
  <joint name="wrist" type="continuous"><parent link="quill"/><child link="wrist"/>
    <origin xyz="0 0 -0.05" rpy="0 0 0"/><axis xyz="0 0 1"/><limit effort="5" velocity="6"/></joint>
  <link name="tool"/>
  <joint name="tool_fixed" type="fixed"><parent link="wrist"/><child link="tool"/>
    <origin xyz="0.04 0 -0.08" rpy="3.141592653589793 0 0"/></joint>
</robot>
"""


ROBOTS = {"ur5e": (ur5e_urdf, "tool0"), "arm7": (arm7_urdf, "ball"), "rail_scara": (rail_scara_urdf, None)}


def write(tmp_path, name: str, text: str | None = None):
    p = tmp_path / f"{name}.urdf"
    p.write_text(text if text is not None else ROBOTS[name][0]())
    return p
