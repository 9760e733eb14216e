"""dqpose.cli.posefile: the JSON and CSV pose files of `dqpose blend` / `dqpose interpolate`."""
from __future__ import annotations

import csv
import io
import json

import numpy as np
import pytest

from dqpose import dq
from dqpose.cli.posefile import (
    format_blend,
    format_samples,
    read_blend,
    read_interpolate,
    sample_times,
)
from tests.cli._cli import server  # noqa: F401 (a fixture)


def _same(a, b, atol=1e-12):
    s = np.sign(np.sum(a[..., :4] * b[..., :4], axis=-1))[..., None]
    np.testing.assert_allclose(s * a, b, atol=atol)


@pytest.fixture
def poses(make_dqs):
    return make_dqs(4)


def _rows(dqs):
    q, t = dq.to_pose(dqs)
    return np.concatenate([t, q], axis=1)


def test_csv_with_and_without_header_and_weights(tmp_path, poses):
    rows = _rows(poses)
    w = np.array([1.0, 2.0, 0.5, 1.0])
    headed = tmp_path / "p.csv"
    headed.write_text("# measured\nqw,qx,qy,qz,x,y,z,weight\n" + "".join(
        ",".join(repr(float(v)) for v in (*r[3:], *r[:3], wi)) + "\n" for r, wi in zip(rows, w)))
    f = read_blend(str(headed))
    _same(f.dqs, poses)
    np.testing.assert_array_equal(f.weights, w)
    assert f.format == "csv" and f.method is None
    # without a header, the quaternion's order is named by --quaternion-order, never guessed
    bare = tmp_path / "bare.txt"
    bare.write_text("".join(",".join(repr(float(v)) for v in r) + "\n" for r in rows))
    with pytest.raises(ValueError, match=r"^line 1: a row without a header does not say which "
                                         r"number of its quaternion is w: start the file with "
                                         r"the header x,y,z,qx,qy,qz,qw \(x, y, z, w .*\) or "
                                         r"x,y,z,qw,qx,qy,qz \(w first\), or give "
                                         r"--quaternion-order xyzw\|wxyz$"):
        read_blend(str(bare))
    g = read_blend(str(bare), "wxyz")
    _same(g.dqs, poses)
    assert g.weights is None
    xyzw = tmp_path / "xyzw.txt"
    xyzw.write_text("".join(",".join(repr(float(v)) for v in (*r[:3], *r[4:], r[3])) + "\n"
                            for r in rows))
    _same(read_blend(str(xyzw), "xyzw").dqs, poses)
    # a header names the order: x, y, z, w as ROS writes it is read so
    (tmp_path / "ros.csv").write_text("x,y,z,qx,qy,qz,qw\n" + xyzw.read_text())
    _same(read_blend(str(tmp_path / "ros.csv")).dqs, poses)


def test_json_is_the_grpcurl_body(tmp_path, poses):
    rows = _rows(poses)
    body = {"poses": [{"position": dict(zip("xyz", r[:3])),
                       "orientation": dict(zip("wxyz", r[3:]))} for r in rows],
            "weights": [1, 1, 2, 2], "method": "METHOD_DLB"}
    p = tmp_path / "req.json"
    p.write_text(json.dumps(body))
    f = read_blend(str(p))
    _same(f.dqs, poses)
    assert f.method == "dlb" and f.format == "json"
    np.testing.assert_array_equal(f.weights, [1, 1, 2, 2])


def test_an_orientation_is_read_in_the_order_its_key_or_the_flag_names(tmp_path, poses):
    rows = _rows(poses)                        # [x, y, z, qw, qx, qy, qz]
    wxyz, xyzw = rows[:, 3:].tolist(), rows[:, [4, 5, 6, 3]].tolist()
    forms = {"named": ([{"position": r[:3].tolist(), "orientation_xyzw": q}
                        for r, q in zip(rows, xyzw)], None),
             "named_wxyz": ([{"position": r[:3].tolist(), "orientation_wxyz": q}
                             for r, q in zip(rows, wxyz)], None),
             "flag_xyzw": ([{"position": r[:3].tolist(), "orientation": q}
                            for r, q in zip(rows, xyzw)], "xyzw"),
             "flag_wxyz": ([{"position": r[:3].tolist(), "orientation": q}
                            for r, q in zip(rows, wxyz)], "wxyz")}
    for name, (entries, order) in forms.items():
        p = tmp_path / f"{name}.json"
        p.write_text(json.dumps({"poses": entries}))
        _same(read_blend(str(p), order).dqs, poses)
        if order is not None:       # the same file without the flag is refused
            with pytest.raises(ValueError, match=r"^poses\[0\]\.orientation: .* does not say"):
                read_blend(str(p))


def test_keyframes_and_times(tmp_path, poses):
    rows = _rows(poses)
    tk = np.array([0.0, 0.5, 1.0, 2.0])
    p = tmp_path / "k.csv"
    p.write_text("t,x,y,z,qw,qx,qy,qz\n" + "".join(
        ",".join(repr(float(v)) for v in (s, *r)) + "\n" for s, r in zip(tk, rows)))
    f = read_interpolate(str(p))
    np.testing.assert_array_equal(f.times_k, tk)
    _same(f.dqs_k, poses)
    t = sample_times(tk, 0.3)
    assert t[0] == 0.0 and t[-1] == 2.0 and np.all(np.diff(t) > 0)
    np.testing.assert_allclose(np.diff(t[:-1]), 0.3)


@pytest.mark.parametrize("text, message", [
    ("x,y,z,qw,qx,qy,qz\n0,0,0,0,0,0,0\n", r"^poses\[0\]\.orientation: zero quaternion"),
    ("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n0,0,nan,1,0,0,0\n",
     r"^poses\[1\]\.position: contains NaN or infinity"),
    ("0,0,0,1,0,0\n", r"^line 1: expected the columns x,y,z,qw,qx,qy,qz\[,weight\], got 6 values"),
    ("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n0,0,zero,1,0,0,0\n",
     r"^line 3, column z: 'zero' is not a number$"),
    ("# measured\nx,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n0,0,0,1,abc,0,0\n",
     r"^line 4, column qx: 'abc' is not a number$"),
    ("qw,qx,qy,qz,x,y,z,weight\n1,0,0,0,0,0,0,\n", r"^line 2, column weight: '' is not a number$"),
    ("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0\n",
     r"^line 2: expected 7 values \(x,y,z,qw,qx,qy,qz\), got 6$"),
    ("x,y,z,qw,qx,qy\n0,0,0,1,0,0\n", r"^line 1: missing column qz; expected x,y,z,qw,qx,qy,qz"),
    ("x,y,z,qw,qx,qy,qz,colour\n0,0,0,1,0,0,0,red\n",
     r"^line 1: unknown column 'colour'; expected x,y,z"),
    ("x,y,z,qw,qx,qy,qz,weigth\n0,0,0,1,0,0,0,1\n",
     r"^line 1: unknown column 'weigth' \(did you mean 'weight'\?\)$"),
    # a time column means keyframes: blending them would silently drop the times
    ("t,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n1,1,0,0,1,0,0,0\n",
     r"^line 1: column t: a time column means keyframes: .*`dqpose interpolate`$"),
    ('{"poses": [{"orientation": {"w": 1, "q": 2}}]}',
     r"^poses\[0\]\.orientation: unknown key 'q'"),
    ('{"poses": [1]}', r"^poses\[0\]: expected an object"),
    # four numbers whose order nothing names: both ways to name it are shown
    ('{"poses": [{"orientation": [0, 0, 0, 1]}]}',
     r'^poses\[0\]\.orientation: \[0, 0, 0, 1\] does not say which number of the quaternion '
     r'is w: write "orientation_xyzw": \[0, 0, 0, 1\] \(x, y, z, w .*\) or "orientation_wxyz": '
     r'\[0, 0, 0, 1\] \(w first\), or the orientation as an object'),
    ('{"poses": [{"orientation_xyzw": [0, 0, 1]}]}',
     r"^poses\[0\]\.orientation_xyzw: expected four numbers x, y, z, w, got \[0, 0, 1\]$"),
    ('{"poses": [{"orientation_wxyz": [1, 0, 0, 0], "orientation": {"w": 1}}]}',
     r"^poses\[0\]: both 'orientation' and 'orientation_wxyz'; give one orientation$"),
    ('{"poses": [{"orientation_xywz": [0, 0, 0, 1]}]}',
     r"^poses\[0\]: unknown key 'orientation_xywz' \(did you mean 'orientation_xyzw'\?\)$"),
    ('{"poses": [{"orientation": {"w": 1}}], "method": "fancy"}',
     r"^method: unknown value 'fancy'"),
    ("{not json", r"not valid JSON"),
    ('"a string"', r'expected an object with "poses"'),
    ("", r"no poses"),
])
def test_bad_files_say_where(tmp_path, text, message):
    p = tmp_path / ("bad.json" if text.lstrip()[:1] in "{[\"" and text else "bad.csv")
    p.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_blend(str(p))


def test_missing_file_names_the_path(tmp_path):
    with pytest.raises(OSError, match=r"nope\.csv: No such file"):
        read_blend(str(tmp_path / "nope.csv"))


def test_bad_step():
    with pytest.raises(ValueError, match=r"^--step: must be a positive number"):
        sample_times(np.array([0.0, 1.0]), 0.0)
    with pytest.raises(ValueError, match=r"^--step: .* samples; use a larger step"):
        sample_times(np.array([0.0, 1e6]), 1e-6)


def test_output_round_trips(poses):
    mean = dq.dib(poses)
    text = format_blend(mean, 3, 1e-13, "csv")
    row = np.array(next(csv.reader(io.StringIO(text.splitlines()[1]))), dtype=float)
    _same(dq.from_pose(row[3:], row[:3]), mean, atol=1e-11)
    doc = json.loads(format_blend(mean, 3, 1e-13, "json"))
    assert doc["iterations"] == 3
    times = np.array([0.0, 0.25, 0.5, 0.75])
    lines = format_samples(times, poses, "csv").splitlines()
    assert lines[0] == "t,x,y,z,qw,qx,qy,qz" and len(lines) == 5
    back = np.array([list(map(float, line.split(","))) for line in lines[1:]])
    np.testing.assert_allclose(back[:, 0], times)
    _same(dq.from_pose(back[:, 4:], back[:, 1:4]), poses, atol=1e-11)


def test_csv_columns_are_matched_by_name_in_any_order(tmp_path, poses):
    rows = _rows(poses)
    tk = np.array([0.0, 0.5, 1.0, 2.0])
    p = tmp_path / "k.csv"
    p.write_text("qw,qx,qy,qz,T,x,y,z\n" + "".join(
        ",".join(repr(float(v)) for v in (*r[3:], s, *r[:3])) + "\n" for s, r in zip(tk, rows)))
    f = read_interpolate(str(p))
    np.testing.assert_array_equal(f.times_k, tk)
    _same(f.dqs_k, poses)


@pytest.mark.parametrize("text, message", [
    # poses without times: the header is a header, and it says what is missing
    ("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n1,0,0,1,0,0,0\n",
     r"^line 1: missing column t; expected t,x,y,z,qw,qx,qy,qz$"),
    ("x,y,z,qw,qx,qy,qz,weight\n0,0,0,1,0,0,0,1\n1,0,0,1,0,0,0,1\n",
     r"^line 1: column weight: weights belong to poses that are blended"),
    ("t,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n1,1,0,0,one,0,0,0\n",
     r"^line 3, column qw: 'one' is not a number$"),
])
def test_bad_keyframe_files_say_where(tmp_path, text, message):
    p = tmp_path / "k.csv"
    p.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_interpolate(str(p))


# ---- robot poses of a hand-eye capture

def _ur_rows(dqs):
    from dqpose.drivers.rotvec import rotvec_from_pose
    return rotvec_from_pose(dqs)


def test_robot_poses_in_every_form_read_alike(tmp_path, poses):
    from dqpose.cli.posefile import read_robot_poses, robot_poses_json
    names = [f"view_{i}.png" for i in range(len(poses))]
    ur = _ur_rows(poses)                       # [x, y, z, rx, ry, rz]
    rows = _rows(poses)                        # [x, y, z, qw, qx, qy, qz]
    files = {
        "ours.json": robot_poses_json(names, poses, "eye_to_hand"),
        "ur.json": json.dumps({"poses": [{"image": n, "base_to_flange": r.tolist()}
                                         for n, r in zip(names, ur)]}),
        "seven.json": json.dumps([{"image": n, "pose": r.tolist()} for n, r in zip(names, rows)]),
        "ur_mm.csv": "image,x,y,z,rx,ry,rz\n" + "".join(
            f"{n},{','.join(repr(float(v)) for v in np.r_[1000 * r[:3], r[3:]])}\n"
            for n, r in zip(names, ur)),
        "plain.csv": "".join(",".join(repr(float(v)) for v in r) + "\n" for r in rows),
        "named.csv": "".join(f"{n}," + ",".join(repr(float(v)) for v in r) + "\n"
                             for n, r in zip(names, rows)),
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        if name in ("seven.json", "plain.csv", "named.csv"):    # seven numbers: order named
            with pytest.raises(ValueError, match="does not say which number"):
                read_robot_poses(str(tmp_path / name))
        got = read_robot_poses(str(tmp_path / name), order="wxyz")
        _same(got.base_flange, poses, atol=1e-12)
        assert got.images == (names if name != "plain.csv" else [None] * len(poses)), name
        said = " ".join(got.notes)
        assert ("rotation vectors" in said) == name.startswith("ur"), (name, said)
        assert ("millimetres" in said) == name.endswith("mm.csv"), (name, said)
    assert read_robot_poses(str(tmp_path / "ours.json")).setup == "eye_to_hand"
    # told the units, the file is read so: metres in millimetres, or millimetres by the file's key
    (tmp_path / "mm.json").write_text(json.dumps({"units": "mm", "poses": (
        np.c_[_rows(poses)[:, :3] * 1000, _rows(poses)[:, 3:]]).tolist()}))
    _same(read_robot_poses(str(tmp_path / "mm.json"), order="wxyz").base_flange, poses,
          atol=1e-12)
    small = read_robot_poses(str(tmp_path / "plain.csv"), units="mm", order="wxyz").base_flange
    np.testing.assert_allclose(dq.to_pose(small)[1], dq.to_pose(poses)[1] / 1000, atol=1e-15)


@pytest.mark.parametrize("text, message", [
    ('{"poses": [[0, 0, 0, 0, 0, 0], {"orientation": {"w": 1}}]}',
     "poses[1]: a quaternion pose among rotvec ones"),
    ('{"poses": [[0.1, 0, 0, 0, 0, 0, 1]]}',
     'poses[0]: [0.1, 0, 0, 0, 0, 0, 1] does not say which number of the quaternion is w: '
     'write {"position": [0.1, 0, 0], "orientation_xyzw": [0, 0, 0, 1]} (x, y, z, w as ROS, '
     'Eigen and scipy order them) or {"position": [0.1, 0, 0], "orientation_wxyz": [0, 0, 0, '
     '1]} (w first)'),
    ("a.png,0.1,0,0,0,0,0,1\n", "line 1: a row without a header does not say which number of "
                                "its quaternion is w: start the file with the header "
                                "[image,]x,y,z,qx,qy,qz,qw"),
    ('{"poses": [{"image": "a.png", "pose": [0, 0, 0, 0, 0, 0]}, [0, 0, 0, 0, 0, 0]]}',
     "poses[1]: no image named, while poses[0] names one"),
    ('{"poses": [[0, 0, 0, 0, 0, 90]]}', "poses[0]: rotation vector of 90, beyond 2 pi"),
    ('{"poses": [[0, 0, 0, 0, 0]]}', "poses[0]: expected a pose"),
    ('{"poses": [{"image": "a.png", "base_to_flange": {"position": {"x": 1}, '
     '"orientation": {"w": 2}}}]}', "poses[0].base_to_flange.orientation: quaternion norm 2"),
    ('{"setup": "eye_on_hand", "poses": [[0, 0, 0, 0, 0, 0]]}', "setup: expected eye_in_hand"),
    ('{"poses": [{"image": "a.png", "base_to_flang": [0, 0, 0, 0, 0, 0]}]}',
     "poses[0]: unknown key 'base_to_flang' (did you mean 'base_to_flange'?)"),
    ('{"poses": [{"imag": "a.png", "pose": [0, 0, 0, 0, 0, 0]}]}',
     "poses[0]: unknown key 'imag' (did you mean 'image'?)"),
    ('{"poses": [{"image": "a.png"}]}', "poses[0]: missing key 'base_to_flange'"),
    ('{"poses": [{"positon": {"x": 1}, "orientation": {"w": 1}}]}',
     "poses[0]: unknown key 'positon' (did you mean 'position'?)"),
    ('{"pose": [[0, 0, 0, 0, 0, 0]]}', "unknown key 'pose' (did you mean 'poses'?)"),
    ('{"poses": []}', "no poses"),
    ("image,x,y,z,roll,pitch,yaw\na.png,0,0,0,0,0,0\n", "line 1: columns image,x,y,z,roll"),
    ("a.png,0,0,0,0,0\n", "line 1: expected [image,]x,y,z and a quaternion"),
    ("x,y,z,rx,ry,rz\n0,0,zero,0,0,0\n", "line 2: '0,0,zero,0,0,0' are not all numbers"),
])
def test_bad_robot_pose_files_say_where(tmp_path, text, message):
    from dqpose.cli.posefile import read_robot_poses
    path = tmp_path / ("p.csv" if not text.startswith("{") else "p.json")
    path.write_text(text)
    with pytest.raises(ValueError) as e:
        read_robot_poses(str(path))
    assert message in str(e.value)


# ---- as a user meets them: `dqpose` in its own process ----------------------------------------

ROOT = __import__("os").path.dirname(__import__("os").path.dirname(
    __import__("os").path.dirname(__import__("os").path.abspath(__file__))))
H = 0.7071067811865476
POSES_JSON = {"poses": [{"position": {"x": 0.1}, "orientation": {"w": 1}},
                        {"position": {"x": 0.3}, "orientation": {"w": H, "z": H}}],
              "weights": [1, 3]}
LIMITS = {"max_linear_velocity": 0.25, "max_angular_velocity": 1.0,
          "max_linear_acceleration": 1.0, "max_angular_acceleration": 2.0}


def dqpose(*argv, cwd):
    """``dqpose ARGV`` as a user runs it: ``(exit code, stdout, stderr)``."""
    import subprocess
    import sys
    p = subprocess.run([sys.executable, "-m", "dqpose.cli", *argv], cwd=cwd, capture_output=True,
                       text=True, timeout=120)
    return p.returncode, p.stdout, p.stderr


def _with(doc, path, value):
    """``doc`` (deep-copied) with the key at ``path`` (a tuple of keys and indices, the last a
    key) renamed to ``value``, or removed when ``value`` is None."""
    doc = json.loads(json.dumps(doc))
    *to, key = path
    d = doc
    for k in to:
        d = d[k]
    v = d.pop(key)
    if value is not None:
        d[value] = v
    return doc


@pytest.mark.parametrize("command, doc, path, renamed, error", [
    ("blend", POSES_JSON, ("poses", 0, "position"), "positon",
     "poses[0]: unknown key 'positon' (did you mean 'position'?)"),
    ("blend", POSES_JSON, ("poses", 1, "orientation"), "rotation",
     "poses[1]: unknown key 'rotation' (did you mean 'orientation'?)"),
    ("blend", POSES_JSON, ("poses", 0, "position"), "translation",
     "poses[0]: unknown key 'translation' (did you mean 'position'?)"),
    ("blend", POSES_JSON, ("poses", 1, "orientation"), None, "poses[1]: missing key 'orientation'"),
    ("blend", POSES_JSON, ("weights",), "weigths",
     "unknown key 'weigths' (did you mean 'weights'?)"),
    ("blend", POSES_JSON, ("poses",), "pose", "unknown key 'pose' (did you mean 'poses'?)"),
    ("interpolate", {"keyframes": [{"time": 0, "pose": POSES_JSON["poses"][0]},
                                   {"time": 1, "pose": POSES_JSON["poses"][1]}]},
     ("keyframes", 1, "time"), "tme", "keyframes[1]: unknown key 'tme' (did you mean 'time'?)"),
    ("interpolate", {"keyframes": [{"time": 0, "pose": POSES_JSON["poses"][0]},
                                   {"time": 1, "pose": POSES_JSON["poses"][1]}]},
     ("keyframes", 1, "pose"), None, "keyframes[1]: missing key 'pose'"),
    ("plan", {"waypoints": [{"pose": POSES_JSON["poses"][0]},
                            {"pose": POSES_JSON["poses"][1], "blend_radius": 0.0}],
              "limits": LIMITS},
     ("waypoints", 1, "blend_radius"), "blend_raduis",
     "waypoints[1]: unknown key 'blend_raduis' (did you mean 'blend_radius'?)"),
    ("plan", {"waypoints": [{"pose": POSES_JSON["poses"][0]}, {"pose": POSES_JSON["poses"][1]}],
              "limits": LIMITS},
     ("limits", "max_linear_velocity"), "max_linear_velocty",
     "limits: unknown key 'max_linear_velocty' (did you mean 'max_linear_velocity'?)"),
])
@pytest.mark.parametrize("fmt", ["json", "yaml"])
def test_a_misspelt_or_missing_key_is_an_error_naming_it(tmp_path, command, doc, path, renamed,
                                                          error, fmt):
    import yaml
    bad = _with(doc, path, renamed)
    f = tmp_path / f"in.{fmt}"
    f.write_text(json.dumps(bad) if fmt == "json" else yaml.safe_dump(bad))
    code, out, err = dqpose(command, str(f), "--local", cwd=tmp_path)
    assert code == 2 and out == "", (out, err)
    assert err.strip().splitlines()[-1].endswith(error), err
    # the file as it should be is read
    f.write_text(json.dumps(doc) if fmt == "json" else yaml.safe_dump(doc))
    code, out, err = dqpose(command, str(f), "--local", cwd=tmp_path)
    assert code == 0, err


def _blend_csv(sep: str, header: bool) -> str:
    rows = [[0.1, 0, 0, 1, 0, 0, 0, 1], [0.3, 0, 0, 0.7071, 0, 0, 0.7071, 3]]
    lines = (([sep.join(POSE_COLUMNS_W)] if header else [])
             + [sep.join(f"{v:g}" for v in r) for r in rows])
    return "# two measurements\n" + "\n".join(lines) + "\n"


POSE_COLUMNS_W = ("x", "y", "z", "qw", "qx", "qy", "qz", "weight")


@pytest.mark.parametrize("sep", [", ", ";", "\t", " ", "   "],
                         ids=["comma-space", "semicolon", "tab", "space", "spaces"])
@pytest.mark.parametrize("header", [True, False])
def test_csv_with_any_separator_reads_as_with_commas(tmp_path, sep, header):
    (tmp_path / "commas.csv").write_text(_blend_csv(",", header))
    (tmp_path / "other.csv").write_text(_blend_csv(sep, header))
    order = () if header else ("--quaternion-order", "wxyz")
    want = dqpose("blend", "commas.csv", "--local", *order, cwd=tmp_path)
    got = dqpose("blend", "other.csv", "--local", *order, cwd=tmp_path)
    assert want[0] == 0 and got == want, (want, got)


def test_csv_without_a_separator_is_refused_naming_those_tried(tmp_path):
    (tmp_path / "p.csv").write_text("0.1|0|0|1|0|0|0\n0.3|0|0|1|0|0|0\n")
    code, out, err = dqpose("blend", "p.csv", "--local", cwd=tmp_path)
    assert code == 2
    assert err.strip() == ("dqpose blend: error: line 1: no columns found in '0.1|0|0|1|0|0|0': "
                           "tried ',', ';', tab and spaces as separators"), err


def test_a_yaml_file_is_read_like_its_json(tmp_path):
    import yaml
    (tmp_path / "p.json").write_text(json.dumps(POSES_JSON))
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(POSES_JSON))
    (tmp_path / "p").write_text("# no extension: told by its content\n"
                                + yaml.safe_dump(POSES_JSON))
    want = dqpose("blend", "p.json", "--local", cwd=tmp_path)
    assert want[0] == 0, want
    assert dqpose("blend", "p.yaml", "--local", cwd=tmp_path) == want
    assert dqpose("blend", "p", "--local", cwd=tmp_path) == want


@pytest.mark.parametrize("where", ["--local", "server"])
def test_rounded_quaternions_are_taken_and_garbage_is_refused_saying_how_far(tmp_path, server,
                                                                              where):
    from dqpose.rpc.client import Client, InvalidArgument
    exact = ("x,y,z,qw,qx,qy,qz\n0.1,0,0,1,0,0,0\n"
             f"0.3,0,0,{H!r},0,0,{H!r}\n")
    rounded = exact.replace(repr(H), "0.7071")              # norm 0.99999, 1e-5 off
    (tmp_path / "exact.csv").write_text(exact)
    (tmp_path / "rounded.csv").write_text(rounded)
    (tmp_path / "bad.csv").write_text(exact.replace(repr(H), "0.7"))   # 0.0101 off
    args = ["--local"] if where == "--local" else ["--server", server.target]
    want = dqpose("blend", "exact.csv", *args, cwd=tmp_path)
    assert want[0] == 0, want
    got = dqpose("blend", "rounded.csv", *args, cwd=tmp_path)
    assert got[0] == 0, got
    np.testing.assert_allclose(np.loadtxt(io.StringIO(got[1]), delimiter=",", skiprows=1),
                               np.loadtxt(io.StringIO(want[1]), delimiter=",", skiprows=1),
                               atol=1e-12)
    code, out, err = dqpose("blend", "bad.csv", *args, cwd=tmp_path)
    assert code == 2 and err.strip() == (
        "dqpose blend: error: poses[1].orientation: quaternion norm 0.989949494 is not unit "
        "(off by 0.0100505, beyond the tolerance 0.001 within which it is normalised); if it is "
        "a rotation, divide it by its norm"), err
    if where == "server":       # the shipped client: the server sees the rounded quaternion
        q = np.array([[1.0, 0, 0, 0], [0.7071, 0, 0, 0.7071]])
        n = np.linalg.norm(q, axis=1, keepdims=True)
        t = np.array([[0.1, 0, 0], [0.3, 0, 0]])
        sent = dq.from_pose(q / n, t) * n          # orientation sent as written: q
        with Client(server.target) as c:
            np.testing.assert_allclose(c.blend(sent), dq.dib(dq.from_pose(*dq.to_pose(sent))),
                                       atol=1e-12)
            with pytest.raises(InvalidArgument,
                               match=r"^poses\[1\]\.orientation: quaternion norm "
                                     r"0\.989949494 is not unit \(off by 0\.0100505"):
                c.blend(sent * np.array([[1.0], [0.7 / 0.7071]]))
