"""The RTDE wire protocol of a UR controller (protocol version 2), named once.

Two sides speak it: the real robot's client, whose probe runs the handshake before ur-rtde
is let near the network (``service.ur_robot``), and the emulated controller of the simulated
cell (``simulator.rtde_emulator``). Both take the protocol's facts from here: the port, the
packet types, the header, the output variables' types. Source: Universal Robots' RTDE guide,
and what ur-rtde 1.6.5 asks (docs/design.md).

Every packet, either way, is a 3-byte big-endian header, uint16 size (header included) and
uint8 type, then its payload (:func:`packet` makes one, :data:`HEADER` reads one):

- ``V`` request protocol version: uint16 version; answer uint8 1 (accepted) or 0;
- ``v`` controller version: no payload; answer four uint32 (major, minor, bugfix, build);
- ``O`` set up outputs: float64 frequency and the comma-separated variable names
  (:func:`output_setup`, :func:`parse_output_setup`); answer uint8 recipe id (0: refused) and
  the comma-separated type names (``NOT_FOUND`` for an unknown variable);
- ``I`` set up inputs, likewise with the input names; ``S`` start and ``P`` pause: answer
  uint8 1 (done) or 0;
- ``U`` data package: uint8 recipe id and the recipe's values in its order
  (:func:`data_package`); ``M`` text message.

The type names must be the guide's (:data:`OUTPUT_TYPES`, :func:`output_type`): a client
decodes the data packages with its own table of them.
"""
from __future__ import annotations

import re
import struct

import numpy as np

from scanner_core.geometry.model import check_rigid

__all__ = ["RTDE_PORT", "PROTOCOL_VERSION", "MAX_FREQUENCY_HZ", "HEADER", "packet",
           "REQUEST_PROTOCOL_VERSION", "GET_URCONTROL_VERSION", "SETUP_OUTPUTS", "SETUP_INPUTS",
           "START", "PAUSE", "DATA_PACKAGE", "TEXT_MESSAGE", "OUTPUT_TYPES", "TYPE_FORMATS",
           "output_type", "output_setup", "parse_output_setup", "data_package",
           "ur_pose", "ur_pose_parts", "ur_pose_to_matrix", "matrix_to_ur_pose"]

#: The RTDE port of a UR controller; ur-rtde's receive interface cannot use another.
RTDE_PORT = 30004
#: The protocol version both sides agree on (ur-rtde 1.6.5 asks for 2).
PROTOCOL_VERSION = 2
#: An e-Series controller's cycle: the highest output frequency, and ur-rtde's default for a
#: controller whose major version is above 3, Hz.
MAX_FREQUENCY_HZ = 500.0

#: The header of every packet: uint16 size (header included), uint8 type.
HEADER = struct.Struct(">HB")

#: Packet types (the guide's RTDE_REQUEST_PROTOCOL_VERSION, RTDE_GET_URCONTROL_VERSION,
#: RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS, ..._SETUP_INPUTS, ..._START, ..._PAUSE,
#: RTDE_DATA_PACKAGE, RTDE_TEXT_MESSAGE).
(REQUEST_PROTOCOL_VERSION, GET_URCONTROL_VERSION, SETUP_OUTPUTS, SETUP_INPUTS, START, PAUSE,
 DATA_PACKAGE, TEXT_MESSAGE) = (ord(c) for c in "VvOISPUM")

#: Output variables of the UR RTDE guide and their types (what the client decodes with its own
#: table, so these must be right); registers are matched by ``_REGISTER``.
OUTPUT_TYPES = {
    "timestamp": "DOUBLE",
    **{name: "VECTOR6D" for name in (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q",
        "actual_qd", "actual_current", "joint_control_output", "actual_TCP_pose",
        "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed",
        "joint_temperatures", "actual_joint_voltage", "ft_raw_wrench", "payload_inertia",
        "actual_current_window", "actual_current_as_torque")},
    **{name: "DOUBLE" for name in (
        "actual_execution_time", "speed_scaling", "target_speed_fraction", "actual_momentum",
        "actual_main_voltage", "actual_robot_voltage", "actual_robot_current",
        "standard_analog_input0", "standard_analog_input1", "standard_analog_output0",
        "standard_analog_output1", "io_current", "euromap67_24V_voltage",
        "euromap67_24V_current", "tool_analog_input0", "tool_analog_input1",
        "tool_output_current", "tool_temperature", "tcp_force_scalar", "payload")},
    **{name: "VECTOR3D" for name in (
        "actual_tool_accelerometer", "elbow_position", "elbow_velocity", "payload_cog")},
    **{name: "INT32" for name in ("robot_mode", "safety_mode", "safety_status",
                                  "tool_output_voltage")},
    **{name: "UINT32" for name in (
        "runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types",
        "euromap67_input_bits", "euromap67_output_bits", "tool_mode", "tool_analog_input_types",
        "output_bit_registers0_to_31", "output_bit_registers32_to_63",
        "input_bit_registers0_to_31", "input_bit_registers32_to_63", "script_control_line")},
    **{name: "UINT64" for name in ("actual_digital_input_bits", "actual_digital_output_bits")},
    "joint_mode": "VECTOR6INT32",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
}
_REGISTER = re.compile(r"(?:output|input)_(int|double|bit)_register_(\d+)$")
_REGISTER_TYPES = {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}
_REGISTER_RANGES = {"int": range(48), "double": range(48), "bit": range(64, 128)}
#: Each type's values in a data package, as ``struct`` codes (big-endian there).
TYPE_FORMATS = {"DOUBLE": "d", "VECTOR3D": "3d", "VECTOR6D": "6d", "INT32": "i", "UINT32": "I",
                "UINT64": "Q", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I", "BOOL": "?",
                "UINT8": "B"}


def packet(kind: int, payload: bytes = b"") -> bytes:
    """One packet of type ``kind``: the header (its size counts the header) and ``payload``."""
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


def output_type(name: str) -> str | None:
    """The RTDE type of output variable ``name`` (``"VECTOR6D"``, ...), None if unknown."""
    if name in OUTPUT_TYPES:
        return OUTPUT_TYPES[name]
    m = _REGISTER.match(name)
    if m is not None and int(m.group(2)) in _REGISTER_RANGES[m.group(1)]:
        return _REGISTER_TYPES[m.group(1)]
    return None


def output_setup(frequency: float, names) -> bytes:
    """The payload of an output setup (``O``): float64 ``frequency``, Hz, and the names."""
    return struct.pack(">d", frequency) + ",".join(names).encode("ascii")


def parse_output_setup(payload: bytes) -> tuple[float, list[str]]:
    """(frequency, Hz; the variable names) of an output setup's payload.

    Raises
    ------
    ValueError
        Shorter than its frequency, or names that are not ASCII.
    """
    if len(payload) < 8:
        raise ValueError(f"output setup of {len(payload)} bytes")
    (frequency,) = struct.unpack_from(">d", payload)
    try:
        names = [n.strip() for n in payload[8:].decode("ascii").split(",") if n.strip()]
    except UnicodeDecodeError as exc:
        raise ValueError("output names are not ASCII") from exc
    return frequency, names


def data_package(types) -> struct.Struct:
    """The layout of a data package (``U``) for a recipe of these type names: uint8 recipe id,
    then each variable's values."""
    return struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in types))


# -- the controller's pose: [x, y, z] m and a rotation vector, rad -----------------------------

#: The controller's unit of length in mm.
MM_PER_M = 1000.0


def ur_pose_parts(ur_pose) -> tuple[np.ndarray, np.ndarray]:
    """A UR pose ``[x, y, z, rx, ry, rz]`` (m; rotation vector: axis times angle, rad), as the
    controller reports and takes it -> ((3,) position, mm; (3,) rotation vector, rad).

    ValueError unless six finite numbers."""
    v = np.asarray(ur_pose, dtype=np.float64)
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise ValueError(f"a UR pose must be six finite numbers [x, y, z (m), rx, ry, rz (rad)], "
                         f"got {np.asarray(ur_pose).tolist()!r}")
    return v[:3] * MM_PER_M, v[3:].copy()


def ur_pose(position_mm, rotvec) -> np.ndarray:
    """(3,) position, mm, and (3,) rotation vector, rad -> the UR pose (6,) float64, m."""
    return np.concatenate([np.asarray(position_mm, dtype=np.float64) / MM_PER_M,
                           np.asarray(rotvec, dtype=np.float64)])


def ur_pose_to_matrix(ur_pose) -> np.ndarray:
    """A UR pose (`ur_pose_parts`) -> (4, 4) float64 rigid transform, mm. ValueError unless six
    finite numbers."""
    from scipy.spatial.transform import Rotation  # not at import: the io face stays light

    position, rotvec = ur_pose_parts(ur_pose)
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    m[:3, 3] = position
    return m


def matrix_to_ur_pose(matrix) -> np.ndarray:
    """(4, 4) rigid transform, mm -> a UR pose (6,) float64: [x, y, z] m and the rotation
    vector, rad, its angle in [0, pi]. ValueError unless a rigid transform."""
    from scipy.spatial.transform import Rotation

    m = check_rigid(matrix)
    return ur_pose(m[:3, 3], Rotation.from_matrix(m[:3, :3]).as_rotvec())
