"""The RTDE wire format (Universal Robots' Real-Time Data Exchange, protocol version 2), as much
of it as a controller simulator needs: framing, the variable type table, and recipes.

A message is ``uint16 size`` (big-endian, including the 3-byte header), ``uint8 type``, payload.
Data packages (``U``) start with a ``uint8`` recipe id followed by the recipe's fields packed
big-endian in order.
"""
from __future__ import annotations

import re
import socket
import struct
from dataclasses import dataclass, field

# the controller's fixed ports: RTDE, the dashboard server, the secondary (script) interface
RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003

# message types (ASCII letters)
REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

HEADER = struct.Struct(">HB")

FORMATS = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}
SIZES = {t: struct.calcsize(">" + f) for t, f in FORMATS.items()}
VECTOR_LENGTHS = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}

# Output variables a controller publishes (names and types from UR's RTDE guide). Registers are
# matched by pattern below.
_OUTPUTS = {
    "timestamp": "DOUBLE", "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32", "safety_mode": "INT32", "safety_status": "INT32",
    "joint_mode": "VECTOR6INT32",
    "runtime_state": "UINT32", "robot_status_bits": "UINT32", "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32", "tool_mode": "UINT32", "tool_analog_input_types": "UINT32",
    "euromap67_input_bits": "UINT32", "euromap67_output_bits": "UINT32",
    "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "script_control_line": "UINT32",
    "actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64",
    "actual_configurable_digital_input_bits": "UINT64",
    "actual_configurable_digital_output_bits": "UINT64",
    "actual_tool_accelerometer": "VECTOR3D", "payload_cog": "VECTOR3D",
    "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D",
    "tool_output_voltage": "INT32",
}
for _n in ("speed_scaling", "target_speed_fraction", "actual_momentum", "actual_main_voltage",
           "actual_robot_voltage", "actual_robot_current", "standard_analog_input0",
           "standard_analog_input1", "standard_analog_output0", "standard_analog_output1",
           "io_current", "tool_analog_input0", "tool_analog_input1", "tool_output_current",
           "tool_temperature", "tcp_force_scalar", "payload", "euromap67_24V_voltage",
           "euromap67_24V_current"):
    _OUTPUTS[_n] = "DOUBLE"
for _n in ("target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q",
           "actual_qd", "actual_qdd", "actual_current", "actual_moment", "joint_control_output",
           "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose",
           "target_TCP_speed", "joint_temperatures", "actual_joint_voltage", "ft_raw_wrench",
           "payload_inertia", "tcp_offset", "actual_current_as_torque"):
    _OUTPUTS[_n] = "VECTOR6D"

_INPUTS = {
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}

_REGISTER = re.compile(r"^(input|output)_(int|double|bit)_register_(\d+)$")
_REGISTER_TYPES = {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}


def register_type(name: str) -> str | None:
    m = _REGISTER.match(name)
    if not m:
        return None
    kind, index = m.group(2), int(m.group(3))
    limit = 128 if kind == "bit" else 48
    if kind == "bit" and index < 64:
        return None  # bits 0..63 exist only as the packed *_bit_registers words
    return _REGISTER_TYPES[kind] if index < limit else None


def output_type(name: str) -> str | None:
    """The RTDE type of an output variable, or None (the controller answers ``NOT_FOUND``)."""
    return _OUTPUTS.get(name) or register_type(name)


def input_type(name: str) -> str | None:
    """The RTDE type of an input variable, or None (``NOT_FOUND``)."""
    if name.startswith("output_"):
        return None
    return _INPUTS.get(name) or register_type(name)


@dataclass
class Recipe:
    """A negotiated list of variables with one packed layout."""
    id: int
    names: list[str]
    types: list[str]
    frequency: float = 0.0
    _struct: struct.Struct = field(init=False, repr=False)

    def __post_init__(self):
        self._struct = struct.Struct(">" + "".join(FORMATS[t] for t in self.types))

    @property
    def size(self) -> int:
        return self._struct.size

    def pack(self, values: dict) -> bytes:
        """``uint8 id`` + fields; ``values`` maps names to scalars or sequences (missing: zeros)."""
        flat = []
        for n, t in zip(self.names, self.types):
            v = values.get(n)
            if v is None:
                v = [0] * VECTOR_LENGTHS[t] if t in VECTOR_LENGTHS else 0
            if t in VECTOR_LENGTHS:
                flat.extend(v)
            else:
                flat.append(v)
        return bytes([self.id]) + self._struct.pack(*flat)

    def unpack(self, payload: bytes) -> dict:
        """Fields of a data package body (after the recipe id byte). Clients may send fewer bytes
        than the recipe holds; only the complete leading fields are returned."""
        out, off = {}, 0
        for n, t in zip(self.names, self.types):
            size = SIZES[t]
            if off + size > len(payload):
                break
            v = struct.unpack_from(">" + FORMATS[t], payload, off)
            out[n] = list(v) if t in VECTOR_LENGTHS else v[0]
            off += size
        return out


def frame(kind: int, payload: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


def read_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("peer closed the connection")
        buf += chunk
    return bytes(buf)


def header(data) -> tuple[int, int]:
    """A message's ``(size, kind)`` from its first ``HEADER.size`` bytes; the size counts the
    header."""
    size, kind = HEADER.unpack_from(data)
    if size < HEADER.size:
        raise ConnectionError(f"malformed RTDE header: size {size}")
    return size, kind


def read_message(sock: socket.socket) -> tuple[int, bytes]:
    size, kind = header(read_exact(sock, HEADER.size))
    return kind, read_exact(sock, size - HEADER.size)


def request_version(host: str, port: int = RTDE_PORT,
                    timeout: float = 1.0) -> tuple[int, int, int, int]:
    """Ask a controller for its software version (``major, minor, bugfix, build``) with a short
    RTDE exchange; raises ``OSError`` on any failure within ``timeout`` seconds."""
    with socket.create_connection((host, port), timeout=timeout) as s:
        s.settimeout(timeout)
        s.sendall(frame(REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)))
        kind, body = read_message(s)
        if kind != REQUEST_PROTOCOL_VERSION or not body or body[0] != 1:
            raise ConnectionError(f"{host}:{port} refused RTDE protocol version 2")
        s.sendall(frame(GET_URCONTROL_VERSION))
        kind, body = read_message(s)
        if kind != GET_URCONTROL_VERSION or len(body) < 16:
            raise ConnectionError(f"{host}:{port} sent no controller version")
        return struct.unpack(">IIII", body[:16])
