"""Pose files for the command line: JSON or YAML (the grpcurl request body) or CSV in, CSV or JSON
out; the files read through :mod:`dqpose.cli.inputs` (every key checked, any CSV separator).

No gRPC here; the same files work for ``--local`` and for calls to a server.
"""
from __future__ import annotations

import io
import json
from typing import NamedTuple

import numpy as np

from dqpose import dq, trajectory
from dqpose.cli import inputs
from dqpose.cli.inputs import document, fields, is_number, load, nearest, not_a_number, table
from dqpose.errors import rename

POSE_COLUMNS = ("x", "y", "z", "qw", "qx", "qy", "qz")


class BlendFile(NamedTuple):
    dqs: np.ndarray
    weights: np.ndarray | None
    method: str | None
    format: str


class InterpolateFile(NamedTuple):
    times_k: np.ndarray
    dqs_k: np.ndarray
    times: np.ndarray | None
    mode: str | None
    format: str


def _answer(fmt: str) -> str:
    """The format of the answer to a file: CSV for CSV, JSON for JSON and YAML."""
    return "csv" if fmt == "csv" else "json"


def parse_floats(name: str, text: str) -> np.ndarray:
    try:
        return np.array([float(v) for v in text.split(",") if v.strip()], dtype=np.float64)
    except ValueError:
        raise ValueError(f"{name}: expected comma-separated numbers, got {text!r}") from None


def _json_poses(field: str, entries, stamped: tuple[str, ...] = (), order: str | None = None):
    """The poses of a list, each a ``Pose`` or, with ``stamped`` (the entry's keys besides
    ``pose``), ``{"time": ..., "pose": ...}``: ``(entries with checked keys, times, (n, 7)
    rows)``; ``order``: ``--quaternion-order``."""
    if not isinstance(entries, list):
        raise ValueError(f"{field}: expected a list")
    checked, times, rows = [], [], []
    for i, e in enumerate(entries):
        where = f"{field}[{i}]"
        if stamped:
            e = fields(where, e, ("pose",) + stamped, required=("pose",))
            times.append(_optional_number(e, "time", where) or 0.0)
            rows.append(inputs.pose(where + ".pose", e["pose"], order))
        else:
            rows.append(inputs.pose(where, e, order))
        checked.append(e)
    return checked, np.array(times), np.array(rows, dtype=np.float64).reshape(-1, 7)


def _numbers(field: str, value) -> np.ndarray | None:
    if value is None or (isinstance(value, list) and not value):
        return None
    try:
        return np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{field}: expected a list of numbers, got {value!r}") from None


def csv_rows(text: str, columns: tuple[str, ...], optional: tuple[str, ...] = (),
              refused: dict[str, str] | None = None, names_out: list | None = None,
              order: str | None = None, taken: tuple[str, ...] = ()) -> np.ndarray:
    """Rows of ``columns`` (+ any ``optional`` present). A first line with no number in it is a
    header: columns are then matched by name, and a missing one, an unknown one, or one named
    in ``refused`` (name -> why) is an error. Without a header the columns are positional, the
    quaternion's (qw, qx, qy, qz in ``columns``) in ``order`` (``--quaternion-order``), which
    such a file needs. ``names_out``, a list, receives the names of the returned columns;
    ``taken``: the text columns the caller took out of the rows before (named in messages)."""
    lines = table(text)
    if not lines:
        return np.empty((0, len(columns)))
    expected = ",".join(columns) + "".join(f"[,{o}]" for o in optional)
    first_line, first = lines[0]
    if not any(is_number(c) for c in first):
        header = [c.strip().lower() for c in first]
        for c in header:
            if c in (refused or {}):
                raise ValueError(f"line {first_line}: column {c}: {refused[c]}")
            if c not in columns + optional:
                guess = nearest(c, columns + optional)
                raise ValueError(f"line {first_line}: unknown column {c!r}" + (
                    f" (did you mean {guess!r}?)" if guess else f"; expected {expected}"))
        missing = [c for c in columns if c not in header]
        if missing:
            raise ValueError(f"line {first_line}: missing column {missing[0]}; expected "
                             f"{expected}")
        names = list(columns) + [o for o in optional if o in header]
        place = [header.index(c) for c in names]
        width = len(header)
        lines = lines[1:]
    else:
        width = len(first)
        if width not in (len(columns), len(columns) + len(optional)):
            raise ValueError(f"line {first_line}: expected the columns {expected}, got {width} "
                             f"values")
        names = list((columns + optional)[:width])
        if "qw" in names:
            if order is None:
                shown = ",".join(list(taken) + names).replace("qw,qx,qy,qz", "QUATERNION")
                raise inputs.unordered_row(first_line, shown)
            at = names.index("qw")
            given = names[:at] + ["q" + c for c in inputs.ORDERS[order]] + names[at + 4:]
            place = [given.index(c) for c in names]
        else:
            place = list(range(width))
    if names_out is not None:
        names_out[:] = names
    out = np.empty((len(lines), len(place)))
    for i, (n, row) in enumerate(lines):
        if len(row) != width:
            raise ValueError(f"line {n}: expected {width} values ({','.join(names)}), got "
                             f"{len(row)}")
        for j, (k, name) in enumerate(zip(place, names)):
            try:
                out[i, j] = float(row[k])
            except ValueError:
                raise ValueError(f"line {n}, column {name}: {not_a_number(row[k])}") from None
    return out


def _to_dqs(field: str, flat: np.ndarray, sub: str = "") -> np.ndarray:
    try:
        return dq.from_pose(flat[:, :4], flat[:, 4:7])
    except ValueError as e:
        raise rename(e, {"q": f"{field}{{}}{sub}.orientation",
                         "t": f"{field}{{}}{sub}.position"}) from None


def _enum(field: str, value, prefix: str, names: tuple[str, ...]) -> str | None:
    if value in (None, "", 0):
        return None
    v = str(value).lower()
    v = v[len(prefix) + 1:] if v.startswith(prefix + "_") else v
    if v not in names:
        raise ValueError(f"{field}: unknown value {value!r}; expected one of {', '.join(names)}")
    return v


def read_blend(path: str, order: str | None = None) -> BlendFile:
    """Poses to blend; ``order`` (``--quaternion-order``) of quaternions not named one by one."""
    text, fmt = load(path)
    if fmt != "csv":
        doc = fields(path, document(path, text, fmt, "poses"), ("poses", "weights", "method"),
                     required=("poses",))
        _, _, flat = _json_poses("poses", doc["poses"], order=order)
        weights = _numbers("weights", doc.get("weights"))
        method = _enum("method", doc.get("method"), "method", tuple(dq.METHODS))
    else:
        rows = csv_rows(text, POSE_COLUMNS, ("weight",), refused={
            "t": "a time column means keyframes: sample the motion through them with "
                 "`dqpose interpolate`"}, order=order)
        flat = np.concatenate([rows[:, 3:7], rows[:, :3]], axis=1)
        weights = rows[:, 7] if rows.shape[1] == 8 else None
        method = None
    if flat.shape[0] == 0:
        raise ValueError(f"{path}: no poses")
    return BlendFile(_to_dqs("poses", flat), weights, method, _answer(fmt))


def read_interpolate(path: str, order: str | None = None) -> InterpolateFile:
    """Keyframes; ``order`` (``--quaternion-order``) of quaternions not named one by one."""
    text, fmt = load(path)
    times = mode = None
    if fmt != "csv":
        doc = fields(path, document(path, text, fmt, "keyframes"),
                     ("keyframes", "times", "interpolation"), required=("keyframes",))
        _, times_k, flat = _json_poses("keyframes", doc["keyframes"], stamped=("time",),
                                       order=order)
        times = _numbers("times", doc.get("times"))
        mode = _enum("interpolation", doc.get("interpolation"), "interpolation",
                     ("screw", "tool_linear"))
        sub = ".pose"
    else:
        rows = csv_rows(text, ("t",) + POSE_COLUMNS, refused={
            "weight": "weights belong to poses that are blended: `dqpose blend`"}, order=order)
        times_k = rows[:, 0]
        flat = np.concatenate([rows[:, 4:8], rows[:, 1:4]], axis=1)
        sub = ""
    if flat.shape[0] == 0:
        raise ValueError(f"{path}: no keyframes")
    return InterpolateFile(times_k, _to_dqs("keyframes", flat, sub), times, mode, _answer(fmt))


def sample_times(times_k: np.ndarray, step: float) -> np.ndarray:
    """Every ``step`` seconds from the first keyframe time, plus the last keyframe time."""
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"--step: must be a positive number of seconds, got {step!r}")
    t0, t1 = float(np.min(times_k)), float(np.max(times_k))
    n = int(np.floor((t1 - t0) / step * (1 + 1e-12))) + 1
    if n > 10_000_000:
        raise ValueError(f"--step: {step} s gives {n} samples; use a larger step")
    t = t0 + step * np.arange(n)
    return t if t[-1] >= t1 else np.append(t, t1)


def _pose_rows(dqs: np.ndarray) -> np.ndarray:
    q, t = dq.to_pose(dqs.reshape(-1, 8))
    q = np.where(q[:, :1] < 0, -q, q)  # q and -q are one rotation; print w >= 0
    return np.concatenate([t, q], axis=1)


def _pose_json(row) -> dict:
    x, y, z, qw, qx, qy, qz = (float(v) for v in row)
    return {"position": {"x": x, "y": y, "z": z},
            "orientation": {"w": qw, "x": qx, "y": qy, "z": qz}}


def pose_json(pose: np.ndarray) -> dict:
    """One ``(8,)`` pose as the JSON of a proto ``Pose`` (``w >= 0``)."""
    return _pose_json(_pose_rows(pose)[0])


def format_blend(mean: np.ndarray, iterations: int, residual: float, fmt: str) -> str:
    row = _pose_rows(mean)[0]
    if fmt == "json":
        return json.dumps({"pose": _pose_json(row), "iterations": int(iterations),
                           "residual": float(residual)}, indent=2) + "\n"
    return ",".join(POSE_COLUMNS) + "\n" + ",".join(f"{v:.12g}" for v in row) + "\n"


def format_samples(times: np.ndarray, dqs: np.ndarray, fmt: str) -> str:
    rows = _pose_rows(dqs)
    if fmt == "json":
        return json.dumps({"samples": [{"time": float(t), "pose": _pose_json(r)}
                                       for t, r in zip(times, rows)]}, indent=2) + "\n"
    out = io.StringIO()
    out.write("t," + ",".join(POSE_COLUMNS) + "\n")
    np.savetxt(out, np.concatenate([np.asarray(times).reshape(-1, 1), rows], axis=1),
               fmt="%.12g", delimiter=",")
    return out.getvalue()




class PlanFile(NamedTuple):
    dqs: np.ndarray                 # (K, 8) waypoints
    times: np.ndarray               # (K,) 0: as fast as the limits allow
    blend_radii: np.ndarray         # (K,)
    limits: dict                    # the file's limits (trajectory.LIMIT_FIELDS), possibly partial
    rate_hz: float | None
    mode: str | None
    format: str


class StampedFile(NamedTuple):
    times: np.ndarray
    dqs: np.ndarray
    limits: dict
    smoothing: float | None
    rate_hz: float | None
    format: str


def _limits(doc: dict) -> dict:
    limits = fields("limits", doc.get("limits") or {}, trajectory.LIMIT_FIELDS)
    return {k: _optional_number(limits, k, "limits") for k in limits}


def _optional_number(doc: dict, key: str, where: str = "") -> float | None:
    v = doc.get(key)
    if v is None:
        return None
    try:
        return float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{where + '.' if where else ''}{key}: expected a number, "
                         f"got {v!r}") from None


def read_plan(path: str, order: str | None = None) -> PlanFile:
    """Waypoints: JSON as grpcurl sends a ``dqpose.v1.PlanRequest`` (a bare list is the
    waypoints), or CSV ``x,y,z,qw,qx,qy,qz`` with optional ``time`` and ``blend_radius``
    columns (by header); ``order`` (``--quaternion-order``) of quaternions not named one by
    one."""
    text, fmt = load(path)
    if fmt != "csv":
        doc = fields(path, document(path, text, fmt, "waypoints"),
                     ("waypoints", "limits", "rate_hz", "interpolation"), required=("waypoints",))
        wps, times, flat = _json_poses("waypoints", doc["waypoints"],
                                       stamped=("time", "blend_radius"), order=order)
        extra = np.array([[t, _optional_number(w, "blend_radius", f"waypoints[{i}]") or 0.0]
                          for i, (t, w) in enumerate(zip(times, wps))],
                         dtype=np.float64).reshape(-1, 2)
        limits, rate = _limits(doc), _optional_number(doc, "rate_hz")
        mode = _enum("interpolation", doc.get("interpolation"), "interpolation",
                     ("screw", "tool_linear"))
        sub = ".pose"
    else:
        names: list = []
        rows = csv_rows(text, POSE_COLUMNS, ("time", "blend_radius"), names_out=names,
                         order=order)
        flat = np.concatenate([rows[:, 3:7], rows[:, :3]], axis=1)
        extra = np.zeros((len(rows), 2))
        for j, name in enumerate(("time", "blend_radius")):
            if name in names:
                extra[:, j] = rows[:, names.index(name)]
        limits, rate, mode, sub = {}, None, None, ""
    if flat.shape[0] == 0:
        raise ValueError(f"{path}: no waypoints")
    return PlanFile(_to_dqs("waypoints", flat, sub), extra[:, 0], extra[:, 1], limits, rate,
                    mode, _answer(fmt))


def read_stamped(path: str, order: str | None = None) -> StampedFile:
    """Time-stamped poses: JSON as grpcurl sends a ``dqpose.v1.SmoothRequest`` (a bare list is
    the poses), or CSV ``t,x,y,z,qw,qx,qy,qz``; ``order`` (``--quaternion-order``) of
    quaternions not named one by one."""
    text, fmt = load(path)
    if fmt != "csv":
        doc = fields(path, document(path, text, fmt, "poses"),
                     ("poses", "limits", "smoothing", "rate_hz"), required=("poses",))
        _, times, flat = _json_poses("poses", doc["poses"], stamped=("time",), order=order)
        limits = _limits(doc)
        smoothing, rate = _optional_number(doc, "smoothing"), _optional_number(doc, "rate_hz")
        sub = ".pose"
    else:
        rows = csv_rows(text, ("t",) + POSE_COLUMNS, order=order)
        times = rows[:, 0]
        flat = np.concatenate([rows[:, 4:8], rows[:, 1:4]], axis=1)
        limits, smoothing, rate, sub = {}, None, None, ""
    if flat.shape[0] == 0:
        raise ValueError(f"{path}: no poses")
    return StampedFile(times, _to_dqs("poses", flat, sub), limits, smoothing, rate, _answer(fmt))


VELOCITY_COLUMNS = ("vx", "vy", "vz", "wx", "wy", "wz")


def format_trajectory(times: np.ndarray, dqs: np.ndarray, velocities: np.ndarray | None,
                      fmt: str) -> str:
    """Samples as CSV ``t,x,y,z,qw,qx,qy,qz[,vx,vy,vz,wx,wy,wz]`` or as JSON ``{"samples":
    [...]}`` (TrajectorySample fields when there are velocities, else StampedPose)."""
    if velocities is None:
        return format_samples(times, dqs, fmt)
    rows = _pose_rows(dqs)
    if fmt == "json":
        def vec(v):
            return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}
        return json.dumps({"samples": [
            {"time": float(t), "pose": _pose_json(r), "linear_velocity": vec(v[:3]),
             "angular_velocity": vec(v[3:])} for t, r, v in zip(times, rows, velocities)]},
            indent=2) + "\n"
    out = io.StringIO()
    out.write("t," + ",".join(POSE_COLUMNS + VELOCITY_COLUMNS) + "\n")
    np.savetxt(out, np.concatenate([np.asarray(times).reshape(-1, 1), rows, velocities], axis=1),
               fmt="%.12g", delimiter=",")
    return out.getvalue()


# ---- robot poses of a hand-eye capture -----------------------------------------------------------

#: a position coordinate beyond this many metres is no arm's: the file is in millimetres
MAX_METRES = 3.0
UNITS = ("auto", "m", "mm")
_ROTVEC_COLUMNS = ("x", "y", "z", "rx", "ry", "rz")


class RobotPoses(NamedTuple):
    """The flange poses of a capture: ``images[i]`` (None when the file names none) was taken at
    ``base_flange[i]``; ``notes`` say how the file was read (rotation vectors, millimetres)."""
    images: list
    base_flange: np.ndarray
    notes: tuple
    setup: str | None


def _robot_row(field: str, value, order: str | None) -> tuple[str, list[float]]:
    """One pose of a robot pose file: ``("quaternion", [qw, qx, qy, qz, x, y, z])`` or
    ``("rotvec", [x, y, z, rx, ry, rz])``; seven numbers are a position and a quaternion in
    ``order`` (``--quaternion-order``), which they need."""
    if isinstance(value, dict):
        return "quaternion", inputs.pose(field, value, order)
    if isinstance(value, (list, tuple)) and len(value) in (6, 7):
        try:
            v = [float(x) for x in value]
        except (TypeError, ValueError):
            raise ValueError(f"{field}: expected numbers, got {value!r}") from None
        if len(v) == 6:
            return "rotvec", v
        if order is None:
            raise inputs.unordered(field, value[3:], position=value[:3]) from None
        q = [v[3 + inputs.ORDERS[order].index(c)] for c in inputs.QUATERNION]
        return "quaternion", q + v[:3]
    raise ValueError(f"{field}: expected a pose: {{\"position\": ..., \"orientation\": ...}}, "
                     f"[x, y, z, rx, ry, rz] (UR) or [x, y, z, then a quaternion in the order "
                     f"--quaternion-order names]")


_ROBOT_ENTRY = ("image", "base_to_flange", "pose")


def _robot_json(path: str, text: str, fmt: str, order: str | None):
    doc = fields(path, document(path, text, fmt, "poses"), ("setup", "units", "poses"),
                 required=("poses",))
    entries = doc["poses"]
    if not isinstance(entries, list):
        raise ValueError(f"{path}: expected \"poses\": a list")
    images, kinds, rows, keys = [], [], [], set()
    for i, e in enumerate(entries):
        field = f"poses[{i}]"
        image, key = None, ""
        # {"image": ..., "base_to_flange" | "pose": POSE}, else a POSE itself
        if (isinstance(e, dict) and not set(e) & set(inputs.POSE_KEYS)
                and set(e) & set(_ROBOT_ENTRY)):
            e = fields(field, e, _ROBOT_ENTRY)
            key = next((k for k in _ROBOT_ENTRY[1:] if k in e), None)
            if key is None:
                raise ValueError(f"{field}: missing key 'base_to_flange'")
            image = e.get("image")
            if image is not None and not isinstance(image, str):
                raise ValueError(f"{field}.image: expected a file name, got {image!r}")
            e, field = e[key], f"{field}.{key}"
        keys.add(key)
        kind, row = _robot_row(field, e, order)
        images.append(image)
        kinds.append(kind)
        rows.append(row)
    sub = f".{keys.pop()}" if len(keys) == 1 and "" not in keys else ""
    return doc, images, kinds, rows, sub


def _robot_csv(text: str, order: str | None):
    lines = table(text)
    header = None
    if lines and not any(is_number(c) for c in lines[0][1][1:]):
        n, header = lines.pop(0)
        header = [c.lower() for c in header]
        for columns in (("image",) + POSE_COLUMNS, ("image",) + _ROTVEC_COLUMNS, POSE_COLUMNS,
                        _ROTVEC_COLUMNS):
            if sorted(header) == sorted(columns):
                break
        else:
            raise ValueError(f"line {n}: columns {','.join(header)}; expected [image,]"
                             f"{','.join(POSE_COLUMNS)} or [image,]{','.join(_ROTVEC_COLUMNS)} "
                             f"(UR rotation vectors)")
    images, kinds, rows = [], [], []
    for n, row in lines:
        if header is not None:
            if len(row) != len(header):
                raise ValueError(f"line {n}: expected {len(header)} values, got {len(row)}")
            cells = dict(zip(header, row))
            image = cells.pop("image", None)
            names = POSE_COLUMNS if "qw" in cells else _ROTVEC_COLUMNS
            values = [cells[c] for c in names]
        else:
            image = None if is_number(row[0]) else row[0]
            values = row[1:] if image is not None else row
            if len(values) not in (6, 7):
                raise ValueError(f"line {n}: expected [image,]x,y,z and a quaternion or "
                                 f"[image,]x,y,z,rx,ry,rz, got {len(row)} values")
            if len(values) == 7:
                if order is None:
                    raise inputs.unordered_row(n, "[image,]x,y,z,QUATERNION")
                values = values[:3] + [values[3 + inputs.ORDERS[order].index(c)]
                                       for c in inputs.QUATERNION]
        try:
            v = [float(c) for c in values]
        except ValueError:
            raise ValueError(f"line {n}: {','.join(values)!r} are not all numbers") from None
        images.append(image)
        kinds.append("rotvec" if len(v) == 6 else "quaternion")
        rows.append(v if len(v) == 6 else v[3:] + v[:3])
    return {}, images, kinds, rows, ""


def read_robot_poses(path: str, units: str = "auto", order: str | None = None) -> RobotPoses:
    """The flange poses ``T_base_flange`` of a hand-eye capture, one per image: JSON
    ``{"setup": ..., "units": "m"|"mm", "poses": [{"image": NAME, "base_to_flange": POSE}]}`` (a
    bare list is the poses; POSE is a pose object (:func:`inputs.pose`), ``[x, y, z, rx, ry,
    rz]`` (a UR rotation vector) or seven numbers x, y, z and a quaternion in ``order``), or CSV
    ``[image,]x,y,z,qw,qx,qy,qz`` (by header, any order; without one, the quaternion in
    ``order``) or ``[image,]x,y,z,rx,ry,rz``. ``order`` is ``--quaternion-order``: quaternions
    not named one by one are refused without it. ``units`` ``auto`` reads positions as
    millimetres when a coordinate is beyond :data:`MAX_METRES` (the file's ``"units"`` wins over
    ``auto``); the returned notes say so, and that rotation vectors were read."""
    if units not in UNITS:
        raise ValueError(f"units: expected one of {', '.join(UNITS)}, got {units!r}")
    text, fmt = load(path)
    doc, images, kinds, rows, sub = _robot_json(path, text, fmt, order) if fmt != "csv" else \
        _robot_csv(text, order)
    if not rows:
        raise ValueError(f"{path}: no poses")
    if len(set(kinds)) > 1:
        i = kinds.index("rotvec" if kinds[0] == "quaternion" else "quaternion")
        raise ValueError(f"poses[{i}]: a {kinds[i]} pose among {kinds[0]} ones; use one form")
    named = [i for i, im in enumerate(images) if im is not None]
    if named and len(named) != len(images):
        i = next(i for i, im in enumerate(images) if im is None)
        raise ValueError(f"poses[{i}]: no image named, while poses[{named[0]}] names one")
    setup = doc.get("setup")
    if setup is not None and setup not in ("eye_in_hand", "eye_to_hand"):
        raise ValueError(f"setup: expected eye_in_hand or eye_to_hand, got {setup!r}")
    a = np.array(rows, dtype=np.float64)
    notes = []
    if units == "auto":
        units = doc.get("units", "auto")
        if units not in UNITS:
            raise ValueError(f"units: expected m or mm, got {units!r}")
    positions = a[:, :3] if kinds[0] == "rotvec" else a[:, 4:7]
    if not np.all(np.isfinite(a)):
        i = int(np.flatnonzero(~np.all(np.isfinite(a), axis=1))[0])
        raise ValueError(f"poses[{i}]: contains NaN or infinity")
    biggest = float(np.abs(positions).max())
    if units == "auto" and biggest > MAX_METRES:
        units = "mm"
        notes.append(f"positions read as millimetres: a coordinate of {biggest:g} is beyond any "
                     f"arm's reach in metres (--units m to read metres)")
    if units == "mm":
        positions /= 1000.0
    if kinds[0] == "rotvec":
        norms = np.linalg.norm(a[:, 3:], axis=1)
        if norms.max() > 2 * np.pi + 1e-9:
            i = int(np.argmax(norms))
            raise ValueError(f"poses[{i}]: rotation vector of {norms[i]:g}, beyond 2 pi: UR "
                             f"rotation vectors [rx, ry, rz] are in radians (degrees given?)")
        from dqpose.drivers.rotvec import pose_from_rotvec
        dqs = pose_from_rotvec(a)
        notes.append("rotations read as UR rotation vectors [x, y, z, rx, ry, rz] (axis times "
                     "angle, radians), not roll-pitch-yaw")
    else:
        dqs = _to_dqs("poses", a, sub)
    return RobotPoses(images, dqs, tuple(notes), setup)


def robot_poses_json(images, base_flange: np.ndarray, setup: str) -> str:
    """The poses file :func:`read_robot_poses` reads (metres, quaternions)."""
    return json.dumps({"setup": setup, "units": "m", "poses": [
        {"image": im, "base_to_flange": pose_json(p)} for im, p in zip(images, base_flange)]},
        indent=1) + "\n"
