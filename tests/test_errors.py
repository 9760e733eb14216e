"""dqpose.errors: the core's argument names replaced by the caller's field paths."""
from dqpose.errors import FieldError, rename


def test_rename_maps_the_core_argument_to_the_field_path():
    e = rename(ValueError("q[3]: zero quaternion"), {"q": "poses{}.orientation"})
    assert isinstance(e, FieldError) and str(e) == "poses[3].orientation: zero quaternion"
    # no index in the core's message: the placeholder disappears
    assert str(rename(ValueError("weights: all weights are zero"), {"weights": "weights{}"})) == \
        "weights: all weights are zero"
    # an unknown name is kept
    assert str(rename(ValueError("x[1]: bad"), {"q": "poses{}"})) == "x[1]: bad"


def test_rename_all_maps_every_argument_the_message_names():
    from dqpose.errors import Infeasible, rename_all
    names = {"a": "pairs{}.first", "b": "pairs{}.second"}
    e = rename_all(Infeasible("a, b[2]: apart; b[2] against a[0]"), names)
    assert str(e) == "pairs.first, pairs[2].second: apart; pairs[2].second against pairs[0].first"
    assert isinstance(e, Infeasible) and isinstance(e, FieldError)
    # whole words only: "ab" is not "a"
    assert str(rename_all(ValueError("ab[1]: x"), names)) == "ab[1]: x"


def test_a_world_error_is_data_named_under_any_field_path():
    from dqpose.errors import WorldError
    e = WorldError(3, "time", "must be finite, got nan")
    assert isinstance(e, FieldError) and str(e) == "measurements[3].time: must be finite, got nan"
    assert e.named("requests[2].measurements", 7) == \
        "requests[2].measurements[7].time: must be finite, got nan"
    assert e.at(7) == WorldError(7, "time", "must be finite, got nan") and e.at(7) != e
    late = WorldError(8, "", "taken at 0.5, beyond the window 0.2 s", about="body 'box'")
    assert str(late) == "measurements[8] (body 'box'): taken at 0.5, beyond the window 0.2 s"
    # the call's own field, and a domain check's ValueError as data
    assert WorldError(None, "options.window", "too long").named("config") == \
        "config.options.window: too long"
    got = WorldError.of(ValueError("poses[0]: not a unit dual quaternion"), 4, {"poses": "pose"})
    assert (got.index, got.field, got.text) == (4, "pose", "not a unit dual quaternion")
    assert str(WorldError.of(ValueError("max_skew: must be nonnegative"), under="options")) == \
        "options.max_skew: must be nonnegative"


def test_domain_errors_are_data_and_their_readers_read_the_fields():
    """A domain check raises a FieldError carrying its field, index, tail and text (its message
    the same as ever); rename, WorldError.of and the Fuse converter read those, not the text: a
    text that looks like a path stays text (a plain ValueError, the C core's, is read)."""
    import numpy as np
    import pytest

    from dqpose import fusion
    from dqpose.errors import WorldError
    from dqpose.rpc.fusion_convert import _domain_error
    with pytest.raises(FieldError) as info:
        fusion.Tracker(1.0, sources=[fusion.Source("cam"), fusion.Source("b", latency=np.nan)])
    e = info.value
    assert (e.field, e.index, e.tail, e.text) == ("sources", 1, ".latency",
                                                  "must be finite, got nan")
    assert str(e) == "sources[1].latency: must be finite, got nan"
    assert str(rename(e, {"sources": "config.sources{}"})) == \
        "config.sources[1].latency: must be finite, got nan"
    with pytest.raises(FieldError) as info:
        fusion.fuse(np.tile([1.0, 0, 0, 0, 0, 0, 0, 0], (2, 1)), weights=[1.0, -2.0])
    assert (info.value.field, info.value.index) == ("weights", 1)
    # no path: the text is not read as one
    plain = FieldError("", "q[1]: not a path")
    assert str(rename(plain, {"q": "poses{}"})) == "q[1]: not a path"
    assert str(rename(ValueError("q[1]: the core's"), {"q": "poses{}"})) == "poses[1]: the core's"
    got = WorldError.of(plain, 2)
    assert (got.field, got.text) == ("", "q[1]: not a path")
    row = _domain_error(FieldError("poses", "not a unit dual quaternion", 1), np.array([4, 9]),
                        "measurements", "options")
    assert str(row) == "measurements[9].pose: not a unit dual quaternion"
    assert str(_domain_error(plain, np.array([4, 9]), "measurements", "options")) == \
        "q[1]: not a path"


def test_each_optional_module_is_in_the_extra_it_is_said_to_be_in():
    """EXTRA_OF against the installed metadata (pyproject.toml's lists): a hint never names an
    extra that does not bring the module."""
    import re
    from importlib import metadata

    from dqpose.errors import EXTRA_OF
    extras: dict[str, set] = {}
    for req in metadata.requires("dqpose"):
        m = re.search(r"extra\s*==\s*['\"]([\w-]+)['\"]", req)
        if m:
            extras.setdefault(m.group(1), set()).add(re.match(r"[\w.-]+", req).group())

    def top_level(dist: str) -> set:    # from the files (ur_rtde's modules are bare .so files)
        return {f.parts[0].split(".")[0] for f in metadata.files(dist) or ()}

    for module, extra in EXTRA_OF.items():   # make installs every extra
        assert any(module in top_level(d) for d in extras[extra]), (module, extra)


def test_the_install_hint_is_what_pip_takes_here(tmp_path, monkeypatch):
    import os

    from dqpose.errors import MissingExtra, install_hint, require
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    monkeypatch.chdir(root)       # make's editable install, from its clone
    assert install_hint("plot") == "install dqpose with the [plot] extra: pip install '.[plot]'"
    monkeypatch.chdir(tmp_path)   # elsewhere: the clone's path
    assert install_hint("plot") == ("install dqpose with the [plot] extra: "
                                    f"pip install '{root}[plot]'")
    require("numpy", "yaml")      # installed: nothing happens
    monkeypatch.setitem(__import__("sys").modules, "yaml", None)   # as if not installed
    try:
        require("numpy", "yaml")
    except MissingExtra as e:
        assert (e.extra, e.module, str(e)) == ("yaml", "yaml", install_hint("yaml"))
    else:
        raise AssertionError("no MissingExtra")
