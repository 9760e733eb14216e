"""Reading the command line's input files, whatever they hold: the format (JSON, YAML or CSV, by
extension, else by content), documents whose every key is checked (an unknown key is an error
naming the nearest known one, a missing required key is an error), and CSV tables split by the
separator they use (comma, semicolon, tab or spaces). ``posefile`` and ``fuse`` read through here,
so a file is read the same way by every command."""
from __future__ import annotations

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


def message(where: str, value, descriptor) -> None:
    """Checks ``value``, a document for the protobuf message of ``descriptor``, key by key at
    every depth with :func:`fields`' rules (protobuf's own parser names only the message type
    and lists every field): ``measurements[0]: unknown key 'positon' (did you mean 'pose'?)``."""
    if not isinstance(value, dict):
        return                  # protobuf's parser says what it expected there
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
                message(f"{at}[{k}]", item, f.message_type)
        elif not f.is_repeated:
            message(at, v, f.message_type)


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
