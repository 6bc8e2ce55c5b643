"""What the deploy tests share: a chained stand-in export (and one with the committed balance policy, for runs
that must stand on the bridge), quick safety timings, a fake robot, a random DDS domain per test, small waits."""

import json
import random
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.deploy.crc import low_cmd_crc
from pipeline.deploy.motors import NUM_MOTORS, MotorMap
from pipeline.deploy.safety import SafetyConfig
from pipeline.deploy.transport import Received, sdk_types

PROVEN = {"unitree-sdk2": "1.0.1", "cyclonedds": "11.0.1"}
SDK = sdk_types()
QUICK = SafetyConfig(damping_s=0.04, ramp_s=0.1, stand_s=0.04, hold_after_s=0.04)
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """A far-jump export with its chain, stand-in networks and the real metadata contract (tests/test_chain.py)."""
    from test_chain import chained_export, standin_task_export

    root = tmp_path_factory.mktemp("deploy")
    return chained_export(standin_task_export(root / "task"), root / "export")


@pytest.fixture(scope="module")
def standing_export(tmp_path_factory):
    """The stand-in task with the committed balance policy the chains use (models/pretrained/balance_landing):
    a chain that stands before the go and after the task, for the runs on the bridge."""
    from test_chain import chained_export, standin_task_export

    root = tmp_path_factory.mktemp("standing")
    return chained_export(standin_task_export(root / "task"), root / "export",
                          balance=REPO / "models" / "pretrained" / "balance_landing" / "export")


def _stance29(export, motors):
    """The balance policy's joint targets at a zero action (the stand-in's), on the 29 motors."""
    stance = json.loads((export / "balance" / "policy.json").read_text())["stance"]["joint_target"]
    return motors.to_motors(np.asarray(stance), 0.0)


def _commands_in(report, robot, mode):
    """The commands written while the controller was in `mode` (one command per tick)."""
    spans = list(zip(report.modes, report.modes[1:] + [(len(robot.commands), None)]))
    return [c for (start, name), (stop, _) in spans if name == mode for c in robot.commands[start:stop]]


def _domain() -> int:
    return random.randint(1, 230)


def _wait(condition, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


class FakeRobot:
    """A LowState source that holds its pose (or follows the commanded q) and records every command."""

    def __init__(self, meta, follow=False, quat=(1.0, 0.0, 0.0, 0.0)):
        self.motors = MotorMap.from_joint_names(meta["joint_names"])
        self.state = SDK.new_low_state()
        self.state.imu_state.quaternion = list(quat)
        self.set_q(np.asarray(meta["default_joint_pos"]) + 0.05)  # not at the default pose
        self.follow, self.silent, self.refused = follow, False, 0
        self.commands: list[dict] = []
        self.latest = None

    def set_q(self, q_joint):
        for i, q in enumerate(self.motors.to_motors(q_joint, 0.0)):
            self.state.motor_state[i].q = float(q)

    def poll(self):
        if not self.silent:
            self.state.tick += 20
            self.latest = Received(self.state, time.monotonic())
        return self.latest

    def write(self, cmd):
        assert low_cmd_crc(cmd) == cmd.crc
        motors = cmd.motor_cmd[:NUM_MOTORS]
        self.commands.append({k: np.array([getattr(m, k) for m in motors]) for k in ("q", "kp", "kd", "mode")})
        if self.follow and cmd.motor_cmd[0].kp > 0:
            self.set_q(self.motors.from_motors(self.commands[-1]["q"]))


def _stop_after(ticks):
    def on_tick(controller):
        if controller.tick >= ticks:
            raise KeyboardInterrupt
    return on_tick
