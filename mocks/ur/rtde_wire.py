"""RTDE wire format (protocol version 2) as a UR e-Series controller speaks it on port 30004.

Every message: ``>HB`` header (total size incl. header, type byte), payload big-endian. Variable names and
types follow Universal Robots' published RTDE guide; a name outside this table is answered with
``NOT_FOUND``, as the controller does (the client then refuses the recipe)."""

from __future__ import annotations

import struct

HEADER = struct.Struct(">HB")

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

# RTDE type name -> struct format (big-endian, without the leading '>')
TYPE_FORMATS = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}

_V6 = "VECTOR6D"
OUTPUTS: dict[str, str] = {
    "timestamp": "DOUBLE", "target_q": _V6, "target_qd": _V6, "target_qdd": _V6, "target_current": _V6,
    "target_moment": _V6, "actual_q": _V6, "actual_qd": _V6, "actual_current": _V6,
    "actual_current_window": _V6, "joint_control_output": _V6, "actual_TCP_pose": _V6, "actual_TCP_speed": _V6,
    "actual_TCP_force": _V6, "target_TCP_pose": _V6, "target_TCP_speed": _V6,
    "actual_digital_input_bits": "UINT64", "joint_temperatures": _V6, "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32", "joint_mode": "VECTOR6INT32", "safety_mode": "INT32", "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D", "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE", "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE", "actual_joint_voltage": _V6, "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32", "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32", "safety_status_bits": "UINT32", "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE", "standard_analog_input1": "DOUBLE", "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE", "io_current": "DOUBLE", "euromap67_input_bits": "UINT32",
    "euromap67_output_bits": "UINT32", "euromap67_24V_voltage": "DOUBLE", "euromap67_24V_current": "DOUBLE",
    "tool_mode": "UINT32", "tool_analog_input_types": "UINT32", "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE", "tool_output_voltage": "INT32", "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE", "tcp_force_scalar": "DOUBLE", "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32", "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32", "tool_output_mode": "UINT8", "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8", "payload": "DOUBLE", "payload_cog": "VECTOR3D",
    "payload_inertia": _V6, "script_control_line": "UINT32", "ft_raw_wrench": _V6,
    "joint_position_deviation_ratio": "DOUBLE", "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "UINT32", "actual_current_as_torque": _V6,
}
INPUTS: dict[str, str] = {
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE", "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8", "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8", "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": _V6,
}
for _i in range(48):
    for _table, _dir in ((OUTPUTS, "output"), (INPUTS, "input")):
        _table[f"{_dir}_int_register_{_i}"] = "INT32"
        _table[f"{_dir}_double_register_{_i}"] = "DOUBLE"
for _i in range(64, 128):
    OUTPUTS[f"output_bit_register_{_i}"] = "BOOL"
    INPUTS[f"input_bit_register_{_i}"] = "BOOL"
# the controller lets clients read back input registers too
for _name, _type in list(INPUTS.items()):
    OUTPUTS.setdefault(_name, _type)


def frame(kind: int, payload: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


def recipe_struct(types: list[str]) -> struct.Struct:
    return struct.Struct(">" + "".join(TYPE_FORMATS[t] for t in types))


def flatten(values: list, types: list[str]) -> list:
    """Recipe values (scalars and vectors) -> flat list for ``struct.pack``."""
    out: list = []
    for v, t in zip(values, types, strict=True):
        if t.startswith("VECTOR"):
            out.extend(v)
        else:
            out.append(v)
    return out


def unflatten(flat: tuple, types: list[str]) -> list:
    out, i = [], 0
    for t in types:
        n = int(TYPE_FORMATS[t][0]) if TYPE_FORMATS[t][0].isdigit() else 1
        out.append(list(flat[i:i + n]) if n > 1 else flat[i])
        i += n
    return out


def split_names(payload: bytes) -> list[str]:
    """Comma-separated variable names; ur_rtde 1.6.5 sends a trailing comma: the empty name is dropped."""
    return [n.strip() for n in payload.decode("ascii", "replace").split(",") if n.strip()]
