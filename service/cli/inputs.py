"""Reading the command line's input files, whatever they hold: the format (JSON, YAML or CSV, by
extension, else by content), documents whose every key is checked (an unknown key is an error
naming the nearest known one, a missing required key is an error), CSV tables split by the
separator they use (comma, semicolon, tab or spaces), and poses, whose orientation order is never
guessed (:func:`pose`, :func:`add_quaternion_order`). ``posefile`` and ``fuse`` read through here,
so a file is read the same way by every command."""
from __future__ import annotations

import argparse
import csv
import difflib
import json
import re
import sys

#: Words people write for a key that has another name here (what difflib cannot guess): the
#: first of the candidates that the object takes is suggested.
SYNONYMS = {"rotation": ("orientation",), "quaternion": ("orientation",), "quat": ("orientation",),
            "rot": ("orientation",), "q": ("orientation",), "translation": ("position",),
            "pos": ("position",), "p": ("position",), "t": ("time", "position"),
            "timestamp": ("time",), "stamp": ("time",)}

#: The CSV separators tried, in order of preference when several fit (None: runs of spaces).
SEPARATORS = ((",", "','"), (";", "';'"), ("\t", "tab"), (None, "spaces"))

_YAML_START = re.compile(r"^(---|- |[A-Za-z_][\w-]*\s*:(\s|$))")


def load(path: str) -> tuple[str, str]:
    """The text of ``path`` (``-``: standard input) and its format, ``json``, ``yaml`` or ``csv``:
    by the extension, else by the first line that is not a comment."""
    if path == "-":
        text = sys.stdin.read()
    else:
        try:
            with open(path, encoding="utf-8") as f:
                text = f.read()
        except OSError as e:
            raise OSError(f"{path}: {e.strerror}") from None
    low = path.lower()
    for fmt, ends in (("json", (".json",)), ("yaml", (".yaml", ".yml")), ("csv", (".csv", ".txt"))):
        if low.endswith(ends):
            return text, fmt
    first = next((line.strip() for line in text.splitlines()
                  if line.strip() and not line.lstrip().startswith("#")), "")
    if first[:1] in ("{", "["):
        return text, "json"
    return text, "yaml" if _YAML_START.match(first) else "csv"


def document(path: str, text: str, fmt: str, key: str) -> dict:
    """The object a JSON or YAML file holds; a bare list is taken as the list under ``key``."""
    if fmt == "yaml":
        from dqpose.errors import missing
        try:
            import yaml
        except ModuleNotFoundError as e:
            raise missing(e) from None
        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ValueError(f"{path}: not valid YAML ({e})") from None
    else:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not valid JSON ({e})") from None
    doc = {key: doc} if isinstance(doc, list) else doc
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected an object with \"{key}\" or a list of {key}")
    return doc


def fields(where: str, value, known: tuple[str, ...], required: tuple[str, ...] = ()) -> dict:
    """``value``, an object, with its keys checked against ``known`` and named as there (the
    protobuf JSON spelling, ``blendRadius`` for ``blend_radius``, is taken too): an unknown key
    is an error naming the nearest known one, a missing ``required`` one an error too."""
    if not isinstance(value, dict):
        raise ValueError(f"{where}: expected an object with {', '.join(known)}, got {value!r}")
    out = {}
    for k, v in value.items():
        name = k if k in known else re.sub(r"(?<=[a-z0-9])([A-Z])", r"_\1", str(k)).lower()
        if name not in known:
            guess = nearest(str(k), known)
            raise ValueError(f"{where}: unknown key {k!r}"
                             + (f" (did you mean {guess!r}?)" if guess
                                else f"; expected {', '.join(known)}"))
        out[name] = v
    for name in required:
        if name not in out:
            raise ValueError(f"{where}: missing key {name!r}")
    return out


def message(where: str, value, descriptor, order: str | None = None) -> None:
    """Checks ``value``, a document for the protobuf message of ``descriptor``, key by key at
    every depth with :func:`fields`' rules (protobuf's own parser names only the message type
    and lists every field): ``measurements[0]: unknown key 'positon' (did you mean 'pose'?)``.
    Every ``Pose`` in it is read by :func:`pose` and written back as protobuf's JSON has it
    (an orientation left out stays out: the zero quaternion, which the request's checks
    refuse)."""
    if not isinstance(value, dict):
        return                  # protobuf's parser says what it expected there
    if descriptor.full_name == POSE_MESSAGE:
        row = pose(where, value, order, required=False)
        value.clear()
        value["position"] = dict(zip(VECTOR, row[-3:]))
        if len(row) == 7:
            value["orientation"] = dict(zip(QUATERNION, row[:4]))
        return
    known = tuple(f.name for f in descriptor.fields)
    named = fields(where, value, known)
    for f in descriptor.fields:
        if f.message_type is None or f.name not in named or f.message_type.GetOptions().map_entry:
            continue
        if f.message_type.full_name.startswith("google.protobuf."):
            continue            # well-known types have JSON forms of their own
        v = named[f.name]
        at = f"{where}.{f.name}" if where else f.name
        if f.is_repeated and isinstance(v, list):
            for k, item in enumerate(v):
                message(f"{at}[{k}]", item, f.message_type, order)
        elif not f.is_repeated:
            message(at, v, f.message_type, order)


#: The orders four quaternion numbers not named one by one (an array, a headerless CSV row) may be
#: in: the order's name -> the components in that order. Both readings of four numbers are valid
#: rotations ([0, 0, 0, 1] is the identity as x, y, z, w and a half turn about z as w, x, y, z),
#: so the order is never guessed: ``orientation_xyzw`` / ``orientation_wxyz`` or
#: ``--quaternion-order`` names it.
ORDERS = {"xyzw": ("x", "y", "z", "w"), "wxyz": ("w", "x", "y", "z")}
QUATERNION, VECTOR = ("w", "x", "y", "z"), ("x", "y", "z")
ORIENTATION_KEYS = ("orientation",) + tuple(f"orientation_{o}" for o in ORDERS)
POSE_KEYS = ("position",) + ORIENTATION_KEYS
#: the protobuf message whose documents :func:`message` reads as :func:`pose` does
POSE_MESSAGE = "dqpose.v1.Pose"


def add_quaternion_order(p: argparse.ArgumentParser) -> None:
    """``--quaternion-order``, of every command that reads poses from a file."""
    p.add_argument("--quaternion-order", choices=tuple(ORDERS), default=None,
                   help="the order of quaternions given as bare arrays or CSV rows without a "
                        "header: xyzw (ROS, Eigen's coeffs(), scipy) or wxyz (default: none; "
                        "such input is refused, as both readings are rotations)")


def unordered(where: str, numbers, position=None) -> ValueError:
    """The error of four quaternion numbers whose order nothing names (after a ``position``: a
    robot pose's seven numbers), showing both ways to name it."""
    v = json.dumps(list(numbers))
    at = "" if position is None else f"{{\"position\": {json.dumps(list(position))}, "
    end = "" if position is None else "}"
    return ValueError(
        f"{where}: {json.dumps(list(position or []) + list(numbers))} does not say which "
        f"number of the quaternion is w: write {at}\"orientation_xyzw\": {v}{end} (x, y, z, w "
        f"as ROS, Eigen and scipy order them) or {at}\"orientation_wxyz\": {v}{end} (w first), "
        f"or the orientation as an object {{\"w\": .., \"x\": .., \"y\": .., \"z\": ..}}; "
        f"--quaternion-order xyzw|wxyz names the order of every such array")


def unordered_row(line: int, columns: str) -> ValueError:
    """The error of a headerless CSV row holding a quaternion."""
    xyzw, wxyz = (columns.replace("QUATERNION", ",".join("q" + c for c in ORDERS[o]))
                  for o in ORDERS)
    return ValueError(
        f"line {line}: a row without a header does not say which number of its quaternion is "
        f"w: start the file with the header {xyzw} (x, y, z, w as ROS, Eigen and scipy order "
        f"them) or {wxyz} (w first), or give --quaternion-order xyzw|wxyz")


def vector(where: str, value, names: tuple[str, ...]) -> list[float]:
    """A vector given as an object (a key left out is 0, as protobuf's JSON has it) or a list
    (a position's [x, y, z])."""
    if value is None:
        return [0.0] * len(names)
    if isinstance(value, dict):
        value = fields(where, value, names)
        value = [value.get(k, 0.0) for k in names]
    if not isinstance(value, (list, tuple)) or len(value) != len(names):
        raise ValueError(f"{where}: expected [{', '.join(names)}] or an object with those keys")
    try:
        return [float(v) for v in value]
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected numbers, got {value!r}") from None


def orientation(where: str, key: str, value, order: str | None) -> list[float]:
    """``[w, x, y, z]`` of ``value``, the pose's entry ``key`` (one of
    :data:`ORIENTATION_KEYS`): an object with named components, or four numbers in the order
    the key names, else ``order`` (``--quaternion-order``), else an error."""
    at = f"{where}.{key}"
    if key == "orientation" and isinstance(value, dict):
        return vector(at, value, QUATERNION)
    named = key[len("orientation_"):] if key != "orientation" else order
    if isinstance(value, (list, tuple)) and len(value) == 4:
        if named is None:
            raise unordered(at, value)
        numbers = vector(at, value, ORDERS[named])
        return [numbers[ORDERS[named].index(c)] for c in QUATERNION]
    if key == "orientation":
        raise ValueError(f"{at}: expected an object {{\"w\": .., \"x\": .., \"y\": .., "
                         f"\"z\": ..}}, or \"orientation_xyzw\" / \"orientation_wxyz\": "
                         f"four numbers, got {value!r}")
    raise ValueError(f"{at}: expected four numbers {', '.join(ORDERS[named])}, got {value!r}")


def pose(where: str, value, order: str | None = None, required: bool = True) -> list[float]:
    """``[qw, qx, qy, qz, x, y, z]`` of a pose object: ``position`` (an object or [x, y, z]; a
    missing one is the origin) and one of :data:`ORIENTATION_KEYS` (missing: an error, or
    ``[]`` for the orientation when not ``required``)."""
    p = fields(where, value, POSE_KEYS)
    given = [k for k in ORIENTATION_KEYS if k in p]
    position = vector(f"{where}.position", p.get("position"), VECTOR)
    if len(given) > 1:
        raise ValueError(f"{where}: both {given[0]!r} and {given[1]!r}; give one orientation")
    if not given:
        if required:
            raise ValueError(f"{where}: missing key 'orientation'")
        return position
    return orientation(where, given[0], p[given[0]], order) + position


def nearest(key: str, known: tuple[str, ...]) -> str | None:
    """The known key ``key`` most likely stands for (a synonym, else the closest spelling), or
    None when none is close."""
    guess = next((g for g in SYNONYMS.get(key.lower(), ()) if g in known), None)
    if guess is None:
        close = difflib.get_close_matches(key.lower(), known, n=1, cutoff=0.6)
        guess = close[0] if close else None
    return guess


def is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def table(text: str) -> list[tuple[int, list[str]]]:
    """The lines of a CSV file that are neither blank nor ``#`` comments, as ``(line number,
    cells)``. The separator is the one of :data:`SEPARATORS` that splits the first line into
    columns and most other lines into as many (then: the most numbers); none: an error naming
    those tried. A line of another width is left to the caller to report."""
    lines = [(n, line) for n, line in enumerate(text.splitlines(), 1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        return []
    best, best_score = None, None
    for sep, _ in SEPARATORS:
        sample = [_split(line, sep) for _, line in lines[:_SAMPLE]]
        width = len(sample[0])
        if width < 2:
            continue
        score = (sum(len(r) == width for r in sample), sum(is_number(c) for r in sample for c in r))
        if best_score is None or score > best_score:
            best, best_score = sep, score
    if best_score is None:
        tried = ", ".join(name for _, name in SEPARATORS[:-1]) + " and " + SEPARATORS[-1][1]
        raise ValueError(f"line {lines[0][0]}: no columns found in {lines[0][1].strip()[:60]!r}: "
                         f"tried {tried} as separators")
    return [(n, _split(line, best)) for n, line in lines]


_SAMPLE = 100       # lines that decide the separator (a recording can have a million)


def _split(line: str, sep: str | None) -> list[str]:
    cells = next(csv.reader([line], delimiter=sep)) if sep else line.split()
    return [c.strip() for c in cells]


def not_a_number(cell: str) -> str:
    """Why ``cell`` is not read as a number, for an error message."""
    if re.fullmatch(r"\s*[-+]?\d+,\d+\s*", cell):
        return f"{cell!r} is not a number (a decimal comma? write {cell.strip().replace(',', '.')})"
    return f"{cell!r} is not a number"
