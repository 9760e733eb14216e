"""dqpose.record's entry points: the null recorder does nothing, and a recorder without the
[record] extra names it."""
import pytest

from dqpose import record
from dqpose.errors import MissingExtra


def test_the_null_recorder_takes_every_call_and_does_nothing():
    call = record.NULL.call("dqpose.v1.Fusion/StreamFuse", object, object)
    call.request(b"x")
    call.answer(b"y")
    call.end("OK")
    record.NULL.plan("p", [[1, 0, 0, 0, 0, 0, 0, 0]])
    assert record.NULL.written == record.NULL.dropped == 0 and not call.alive


@pytest.mark.parametrize("module", record.MODULES)
def test_a_recorder_without_the_extra_names_it(tmp_path, monkeypatch, module):
    monkeypatch.setitem(__import__("sys").modules, module, None)   # as if not installed
    with pytest.raises(MissingExtra, match=r"\[record\] extra") as e:
        record.open_recorder(tmp_path)
    assert e.value.extra == "record" and e.value.module == module
    assert list(tmp_path.iterdir()) == []


def test_a_live_recorder_without_websockets_names_the_record_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "websockets", None)
    with pytest.raises(MissingExtra, match=r"\[record\] extra") as e:
        record.open_recorder(None, live=("127.0.0.1", 0))
    assert e.value.module == "websockets"
