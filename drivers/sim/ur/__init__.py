"""A simulated Universal Robots e-series controller that the unmodified ``ur_rtde`` client drives.

It speaks the controller's own protocols on one address (ports are fixed, so run one simulator
per loopback address, e.g. ``127.0.0.2``):

* RTDE on 30004: handshake (``V v O I S P``), data packages at the requested rate, input recipes
  written into one register table (:mod:`.rtde_server`);
* the dashboard server on 29999 (banner, version, serial number, program and safety commands);
* the script port 30003: an uploaded program (``def ...: ... end``) starts playing at once
  (both :mod:`.dashboard`).

The controller's model (:mod:`.model`): the uploaded ``rtde_control`` script's register
protocol, tool-space servoL, moveL and stops. Test hooks are JSON lines on ``HOOK_PORT`` of the
same address (:mod:`.hooks`; their client is :class:`URSimProcess`, :mod:`.process`).
:class:`URSim` (:mod:`.server`) is the whole controller in one process; :func:`main`
(:mod:`.cli`) runs it.

Run it with ``dqpose sim ur --host 127.0.0.2`` or ``python -m dqpose.drivers.sim.ur``.
"""
from dqpose.drivers.sim.ur.cli import main
from dqpose.drivers.sim.ur.model import (
    DASHBOARD_PORT,
    EMERGENCY_STOP_BIT,
    HOOK_PORT,
    MOVEL,
    NORMAL_MODE,
    PAUSED,
    PAUSING,
    PLAYING,
    PROTECTIVE_STOP_BIT,
    REALTIME,
    RTDE_PORT,
    SCRIPT_PORT,
    SERVO_STOP,
    SERVOL,
    SPEED_STOP,
    STOP_SCRIPT,
    STOPJ,
    STOPL,
    STOPPED,
    STOPPING,
    Controller,
    SimConfig,
)

# address_free: the tests pick a free loopback address with it too
from dqpose.drivers.sim.ur.process import (  # noqa: F401
    URSimProcess,
    address_free,
    servo_lag_cycles,
)
from dqpose.drivers.sim.ur.server import URSim

__all__ = ["main", "URSim", "URSimProcess", "SimConfig", "Controller", "servo_lag_cycles",
           "RTDE_PORT", "DASHBOARD_PORT", "SCRIPT_PORT", "HOOK_PORT", "STOPPING", "STOPPED",
           "PLAYING", "PAUSING", "PAUSED", "NORMAL_MODE", "PROTECTIVE_STOP_BIT",
           "EMERGENCY_STOP_BIT", "REALTIME", "SERVOL", "MOVEL", "SPEED_STOP", "SERVO_STOP",
           "STOPL", "STOPJ", "STOP_SCRIPT"]
