"""The arm spec: one grammar and one table of keys for every arm (drivers.spec)."""
from __future__ import annotations

import pytest

from dqpose import drivers
from dqpose.drivers.spec import ARM_KEYS, ArmSpec, key_table, parse_arm_spec, resolve


def test_a_spec_with_keys_parses_to_kind_target_and_options():
    s = parse_arm_spec("ur:192.168.1.10?stale_after=0.3&max_tracking=0.005")
    assert s == ArmSpec("ur", "192.168.1.10", {"stale_after": 0.3, "max_tracking": 0.005})
    assert s.channel == "ur:192.168.1.10"
    assert parse_arm_spec(str(s)) == s
    s = parse_arm_spec("piper:socketcan:can0?max_tracking_angle=0.03")
    assert (s.kind, s.target, s.options) == ("piper", "socketcan:can0",
                                             {"max_tracking_angle": 0.03})
    assert parse_arm_spec("piper:virtual:x").options == {}


@pytest.mark.parametrize("text, message", [
    ("ur:h?stale_timeout=0.3", r"^stale_timeout: unknown arm key in 'ur:h\?stale_timeout=0.3' "
                               r"\(did you mean 'stale_after'\?\); known: stale_after, "),
    ("ur:h?max_trackin=1", r"^max_trackin: unknown arm key .*did you mean 'max_tracking'\?"),
    ("ur:h?stale_after=fast", r"^stale_after: 'fast' is not a number \(s\)$"),
    ("ur:h?stale_after=-1", r"^stale_after: must be a positive number of s, got -1.0$"),
    ("ur:h?stale_after=nan", r"^stale_after: must be a positive number of s, got nan$"),
    ("ur:h?heartbeat=0.1&heartbeat=0.2", r"^heartbeat: given twice in"),
    ("ur:h?", r"^arm: 'ur:h\?' ends in '\?' without key=value$"),
    ("ur:h?heartbeat", r"^arm: 'heartbeat' in 'ur:h\?heartbeat' is not key=value$"),
    ("ur:h?heartbeat=", r"^arm: 'heartbeat=' in .* is not key=value$"),
    ("kuka:h", r"^arm: unknown backend 'kuka' in 'kuka:h'; known: piper, ur "
               r"\(as 'KIND:TARGET\[\?key=value&key=value...\]'\)$"),
    ("ur", r"^arm: 'ur' has no channel; expected 'ur:<channel>'$"),
    ("ur:?heartbeat=1", r"^arm: 'ur:\?heartbeat=1' has no channel"),
])
def test_a_bad_spec_is_refused_naming_what(text, message):
    with pytest.raises(ValueError, match=message):
        parse_arm_spec(text)


def test_every_key_has_a_default_for_every_arm_and_one_line_of_help():
    for kind in drivers.ARMS:
        values = resolve(kind, {})
        assert set(values) == set(ARM_KEYS) and all(v > 0 for v in values.values())
    assert resolve("ur", {})["stale_after"] == 0.1 and resolve("piper", {})["stale_after"] == 0.35
    assert resolve("ur", {"max_tracking": 0.01})["max_tracking"] == 0.01
    lines = key_table().splitlines()
    assert len(lines) == len(ARM_KEYS)
    assert lines[0].startswith("stale_after (s, default piper 0.35, ur 0.1): ")
    with pytest.raises(ValueError, match=r"^stale_timeout: unknown arm key \(did you mean "
                                         r"'stale_after'\?\)"):
        resolve("piper", {"stale_timeout": 0.5})
    with pytest.raises(ValueError, match="^max_tracking: must be a positive number of m"):
        resolve("ur", {"max_tracking": 0})
