"""The G1's low-level DDS interface: `unitree_hg` LowCmd_ on rt/lowcmd, LowState_ on rt/lowstate.

Message types are the Unitree SDK 2's (unitree-sdk2 on PyPI), used with the CycloneDDS Python
binding's wheel on PyPI (cyclonedds 11.0.1; the SDK pins 0.10.2, a source-only release that needs the
C library to build). Proven together here:
unitree-sdk2 1.0.1 + cyclonedds 11.0.1 (tests/test_deploy.py). That SDK wheel's package
`__init__` imports a `b2` subpackage the wheel does not contain, so `import unitree_sdk2py` fails;
`sdk_types()` registers an empty module under that name first. The SDK's channel factory is a
process-wide singleton bound to one domain, so participants, topics, readers and writers are made
here with the binding directly (one domain per link; tests use several).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
import time
import types
from dataclasses import dataclass

from pipeline.deploy.crc import low_cmd_crc, low_state_crc
from pipeline.deploy.motors import NUM_MOTOR_SLOTS

LOW_CMD_TOPIC = "rt/lowcmd"
LOW_STATE_TOPIC = "rt/lowstate"
ODOMETRY_TOPIC = "rt/adamimic/odometry"

_CONFIG = """<?xml version="1.0" encoding="UTF-8" ?>
<CycloneDDS><Domain Id="any"><General><Interfaces>
  <NetworkInterface name="{interface}" priority="default" multicast="default"/>
</Interfaces></General></Domain></CycloneDDS>"""


def sdk_types() -> types.SimpleNamespace:
    """The SDK's unitree_hg message classes and their default constructors."""
    spec = importlib.util.find_spec("unitree_sdk2py")
    if spec is None:
        raise ImportError("unitree-sdk2 is not installed (make setup installs it)")
    if "unitree_sdk2py" not in sys.modules:
        has_b2 = any(os.path.isdir(os.path.join(p, "b2"))
                     for p in spec.submodule_search_locations)
        if not has_b2:  # the 1.0.1 wheel's __init__ imports a subpackage it lacks
            sys.modules.setdefault("unitree_sdk2py.b2", types.ModuleType("unitree_sdk2py.b2"))
    hg = importlib.import_module("unitree_sdk2py.idl.unitree_hg.msg.dds_")
    nav = importlib.import_module("unitree_sdk2py.idl.nav_msgs.msg.dds_")
    default = importlib.import_module("unitree_sdk2py.idl.default")
    return types.SimpleNamespace(LowCmd=hg.LowCmd_, LowState=hg.LowState_, Odometry=nav.Odometry_,
                                 new_low_cmd=default.unitree_hg_msg_dds__LowCmd_,
                                 new_low_state=default.unitree_hg_msg_dds__LowState_,
                                 new_odometry=default.nav_msgs_msg_dds__Odometry_)


def _check(message, slots: list, what: str, crc_of) -> str | None:
    """Why a unitree_hg message must be refused (wrong motor count, bad CRC), or None when it is sound."""
    if len(slots) != NUM_MOTOR_SLOTS:
        return f"has {len(slots)} motor {what}, the G1's {type(message).__name__} carries {NUM_MOTOR_SLOTS}"
    crc = crc_of(message)
    if crc != message.crc:
        return f"CRC mismatch (message says {message.crc:#010x}, contents give {crc:#010x})"
    return None


def check_low_state(state) -> str | None:
    return _check(state, state.motor_state, "states", low_state_crc)


def check_low_cmd(cmd) -> str | None:
    return _check(cmd, cmd.motor_cmd, "commands", low_cmd_crc)


_DOMAINS: dict[int, tuple[object, str]] = {}


class DdsLink:
    """One participant on `domain_id`, bound to one network interface (`lo` for the sim bridge)."""

    def __init__(self, domain_id: int, interface: str):
        from cyclonedds.domain import Domain, DomainParticipant

        self.domain_id, self.interface = int(domain_id), interface
        self.types = sdk_types()
        # CycloneDDS allows one configured Domain per id in a process; links on the same id share it
        if self.domain_id not in _DOMAINS:
            _DOMAINS[self.domain_id] = (Domain(self.domain_id, _CONFIG.format(interface=interface)), interface)
        elif _DOMAINS[self.domain_id][1] != interface:
            raise ValueError(f"DDS domain {self.domain_id} is already bound to {_DOMAINS[self.domain_id][1]!r} "
                             f"in this process, not {interface!r}")
        self.participant = DomainParticipant(self.domain_id)
        self._topics: dict[str, object] = {}

    def topic(self, name: str, kind):
        from cyclonedds.topic import Topic

        if name not in self._topics:
            self._topics[name] = Topic(self.participant, name, kind)
        return self._topics[name]

    def writer(self, name: str, kind):
        from cyclonedds.pub import DataWriter

        return DataWriter(self.participant, self.topic(name, kind))

    def reader(self, name: str, kind, keep_last: int = 1):
        from cyclonedds.qos import Policy, Qos
        from cyclonedds.sub import DataReader

        return DataReader(self.participant, self.topic(name, kind), Qos(Policy.History.KeepLast(keep_last)))


@dataclass
class Received:
    message: object
    time: float  # time.monotonic() when taken


class CheckedReader:
    """The newest sound message of a topic; unsound ones are refused and counted, never returned."""

    def __init__(self, reader, check):
        self.reader, self.check = reader, check
        self.refused = 0
        self.last_refusal: str | None = None
        self.latest: Received | None = None

    def poll(self) -> Received | None:
        """Takes what arrived; returns the newest sound message seen so far (None before any)."""
        for message in reversed(self.reader.take(N=16)):
            if type(message).__name__ == "InvalidSample":  # a writer went away: no data in it
                continue
            problem = self.check(message) if self.check else None
            if problem is not None:
                self.refused += 1
                self.last_refusal = problem
                continue
            self.latest = Received(message, time.monotonic())
            break
        return self.latest


class NullWriter:
    """--dry-run: everything is built and signed, nothing is published."""

    def __init__(self):
        self.withheld = 0

    def write(self, message) -> None:
        self.withheld += 1
