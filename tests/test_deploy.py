"""G1 deployment: CRC and message checks, the safety modes and watchdog, and the controller
against a fake robot, the go key and the odometry topic (tests/test_deploy_bridge.py runs it over DDS).

Proven together: unitree-sdk2 1.0.1 (its unitree_hg types) with cyclonedds 11.0.1 (PROVEN below).
"""

import json
import os
import platform
import shutil
import time
from importlib.metadata import version

import numpy as np
import pytest

from pipeline.common.errors import PipelineInputError
from pipeline.deploy.controller import G1Controller
from pipeline.deploy.crc import low_cmd_crc, low_state_crc
from pipeline.deploy.motors import G1_MOTOR_NAMES, NUM_MOTORS, MotorMap
from pipeline.deploy.safety import Measured, SafetyConfig, Watchdog
from pipeline.deploy.transport import check_low_state

from deploy_helpers import PROVEN, QUICK, SDK, FakeRobot, _commands_in, _domain, _stance29, _stop_after, _wait, export, standing_export  # noqa: F401  (export, standing_export: module fixtures)


# ------------------------------------------------------------------------------ versions, CRC, messages
def test_proven_versions_are_installed():
    assert {name: version(name) for name in PROVEN} == PROVEN


def _random_messages(rng):
    cmd, state = SDK.new_low_cmd(), SDK.new_low_state()
    cmd.mode_machine = 5
    for i, m in enumerate(cmd.motor_cmd):
        m.mode, m.q, m.kp, m.kd, m.tau, m.reserve = 1, *rng.normal(size=4).tolist(), i
    state.tick = 123456
    state.imu_state.quaternion = rng.normal(size=4).tolist()
    for i, m in enumerate(state.motor_state):
        m.q, m.dq, m.tau_est, m.temperature = *rng.normal(size=3).tolist(), [30 + i, -i]
    state.wireless_remote = list(range(40))
    return cmd, state


def test_crc_matches_the_sdks(monkeypatch):
    """Ours (zlib, fast) against the SDK's own packing and bitwise CRC (its pure-Python path: the
    wheel lacks the shared library its Linux path loads)."""
    from unitree_sdk2py.utils import crc as sdk_crc

    monkeypatch.setattr(platform, "system", lambda: "NotLinux")
    reference = sdk_crc.CRC()
    rng = np.random.default_rng(0)
    for _ in range(3):
        cmd, state = _random_messages(rng)
        assert low_cmd_crc(cmd) == reference.Crc(cmd)
        assert low_state_crc(state) == reference.Crc(state)


def test_unsound_low_states_are_refused():
    _, state = _random_messages(np.random.default_rng(1))
    state.crc = low_state_crc(state)
    assert check_low_state(state) is None
    state.motor_state[3].q += 1e-3  # one value changed after signing
    assert "CRC mismatch" in check_low_state(state)
    state.motor_state = state.motor_state[:29]
    assert "29 motor states" in check_low_state(state)


def test_bad_crc_and_wrong_motor_count_over_dds():
    """A LowState with a bad CRC reaches the reader and is refused; one with 29 motor slots cannot
    even be written with the robot's type (a fixed array of 35)."""
    from pipeline.deploy.transport import LOW_STATE_TOPIC, CheckedReader, DdsLink

    link = DdsLink(_domain(), "lo")
    reader = CheckedReader(link.reader(LOW_STATE_TOPIC, SDK.LowState), check_low_state)
    writer = link.writer(LOW_STATE_TOPIC, SDK.LowState)
    good, bad = SDK.new_low_state(), SDK.new_low_state()
    good.tick, bad.tick = 1, 2
    good.crc = low_state_crc(good)
    bad.crc = low_state_crc(bad) ^ 1
    writer.write(good)
    _wait(lambda: reader.poll() is not None)
    writer.write(bad)
    _wait(lambda: (reader.poll(), reader.refused)[1] == 1)
    assert reader.latest.message.tick == 1 and "CRC mismatch" in reader.last_refusal
    short = SDK.new_low_state()
    short.motor_state = short.motor_state[:29]
    with pytest.raises(Exception, match="motor_state"):
        writer.write(short)


# ------------------------------------------------------------------------------ motors and safety
def test_motor_map_puts_27_joints_on_29_motors(export):
    meta = json.loads((export / "policy.json").read_text())
    motors = MotorMap.from_joint_names(meta["joint_names"])
    per_motor = motors.to_motors(np.arange(27.0) + 1, 0.0)
    assert per_motor.shape == (NUM_MOTORS,)
    waist = [G1_MOTOR_NAMES.index("waist_roll_joint"), G1_MOTOR_NAMES.index("waist_pitch_joint")]
    assert np.all(per_motor[waist] == 0)
    assert per_motor[G1_MOTOR_NAMES.index("left_shoulder_pitch_joint")] == 1 + meta["joint_names"].index(
        "left_shoulder_pitch_joint")
    assert np.array_equal(motors.from_motors(per_motor), np.arange(27.0) + 1)
    with pytest.raises(PipelineInputError, match="not motors of the 29-DoF G1"):
        MotorMap.from_joint_names([*meta["joint_names"][:-1], "tail_joint"])
    with pytest.raises(PipelineInputError, match="does not drive"):
        MotorMap.from_joint_names(meta["joint_names"][:-1])


def test_watchdog_reasons():
    limits = np.array([[-1.0, 1.0], [-0.5, 0.5]])
    dog = Watchdog(SafetyConfig(state_timeout_s=0.1, joint_margin_rad=0.1, max_tilt_rad=np.radians(45)), limits,
                   ["a_joint", "b_joint"])
    upright = dict(joint_pos=np.zeros(2), joint_vel=np.zeros(2), gravity=np.array([0, 0, -1.0]),
                   base_ang_vel=np.zeros(3), age_s=0.01)
    assert dog.fault(Measured(**upright)) is None
    assert "LowState stopped" in dog.fault(Measured(**{**upright, "age_s": 0.15}))
    assert dog.fault(Measured(**{**upright, "joint_pos": np.array([0.0, 0.59])})) is None  # inside the margin
    assert "b_joint" in dog.fault(Measured(**{**upright, "joint_pos": np.array([0.0, 0.61])}))
    tilt = np.radians(50)
    assert "tilted 50 deg" in dog.fault(Measured(**{**upright, "gravity": np.array([np.sin(tilt), 0, -np.cos(tilt)])}))
    with pytest.raises(PipelineInputError, match="safety.state_timeout_s"):
        SafetyConfig(state_timeout_s=0)


def _controller(export, robot, **kw):
    kw.setdefault("safety", QUICK)
    return G1Controller(export, 1.4, state_reader=robot, cmd_writer=robot, sdk=SDK,
                        pose_source=kw.pop("pose", lambda: (np.zeros(3), 0.0)), log=lambda line: None, **kw)


def test_damping_then_ramp_then_waits_for_the_go(export):
    meta = json.loads((export / "policy.json").read_text())
    robot = FakeRobot(meta)
    start_q = robot.motors.to_motors(np.asarray(meta["default_joint_pos"]) + 0.05, 0.0)
    report = _controller(export, robot, go=lambda: False, on_tick=_stop_after(12)).run()
    assert [m for _, m in report.modes] == ["damping", "ramp", "stand", "damping"]
    assert report.end == "interrupted" and not report.phases  # no go, no policy step
    first = robot.commands[0]
    assert np.all(first["kp"] == 0) and np.all(first["kd"] > 0)  # damping
    ramp = _commands_in(report, robot, "ramp")
    default29 = robot.motors.to_motors(np.asarray(meta["default_joint_pos"]), 0.0)
    assert np.allclose(ramp[0]["q"], start_q, atol=1e-6)  # from the measured pose ...
    assert np.allclose(ramp[-1]["q"], default29, atol=0.05)  # ... to the default pose
    stand = _commands_in(report, robot, "stand")
    assert stand and all(np.allclose(c["q"], _stance29(export, robot.motors), atol=1e-5) for c in stand)  # the balance policy
    middle = ramp[len(ramp) // 2 - 1]["q"]
    assert np.all((middle - default29) * (start_q - default29) >= -1e-9)  # on the way between them
    waist = [G1_MOTOR_NAMES.index("waist_roll_joint"), G1_MOTOR_NAMES.index("waist_pitch_joint")]
    assert all(np.all(c["q"][waist] == 0) and np.all(c["kp"][waist] > 0) for c in ramp)  # locked waist held at 0
    assert np.all(robot.commands[-1]["kp"] == 0)  # Ctrl-C: damping, not the held pose


def test_ctrl_c_mid_episode_damps_and_policy_targets_go_out_as_trained(export, tmp_path):
    """The policies' targets are sent unclamped, as training and sim2sim apply them (a landing presses an
    ankle past its range for the torque at the stop); only the ramp's stay inside the ranges."""
    narrow = tmp_path / "narrow"
    shutil.copytree(export, narrow)
    meta = json.loads((narrow / "policy.json").read_text())
    default = np.asarray(meta["default_joint_pos"])
    meta["joint_limits"] = np.stack([default - 0.01, default + 0.01], axis=1).tolist()
    (narrow / "policy.json").write_text(json.dumps(meta))
    robot = FakeRobot(meta, follow=True)
    robot.set_q(default)
    report = _controller(narrow, robot, go=lambda: True, on_tick=_stop_after(15),
                         safety=SafetyConfig(damping_s=0.0, ramp_s=0.1, stand_s=0.0, joint_margin_rad=5.0)).run()
    assert report.end == "interrupted" and len(report.phases) >= 5
    policy = [c for c in robot.commands if c["kp"][0] > 0][-len(report.phases):]
    q = np.array([robot.motors.from_motors(c["q"]) for c in policy])
    assert np.abs(q - default).max() > 0.01 + 1e-3  # past the (narrow) ranges: not clamped
    assert report.joint_past_limit_rad > 0.0  # and the report says how far the joints went
    tail = robot.commands[-5:]
    assert all(np.all(c["kp"] == 0) for c in tail)  # damping after Ctrl-C, never the last target


@pytest.mark.parametrize("fault, reason", [("silent", "LowState stopped"), ("joint", "left its range"),
                                           ("tilt", "tilted")])
def test_watchdog_falls_back_to_damping_mid_episode(export, fault, reason):
    meta = json.loads((export / "policy.json").read_text())
    robot = FakeRobot(meta)
    robot.set_q(np.asarray(meta["default_joint_pos"]))

    def on_tick(controller):
        if len(controller.report.phases) == 3:
            if fault == "silent":
                robot.silent = True
            elif fault == "joint":
                robot.state.motor_state[G1_MOTOR_NAMES.index("left_knee_joint")].q = 4.0
            else:
                robot.state.imu_state.quaternion = [float(np.cos(0.7)), 0.0, float(np.sin(0.7)), 0.0]  # 80 deg
        assert controller.tick < 100, "no fault"

    report = _controller(export, robot, go=lambda: True, on_tick=on_tick).run()
    assert report.end == "fault" and reason in report.message and report.exit_code == 3
    # a bad state is caught on the tick it arrives; silence once it is older than state_timeout_s
    late = 1 + int(np.ceil(QUICK.state_timeout_s / 0.02)) if fault == "silent" else 1
    assert 3 <= len(report.phases) <= 3 + late and all(np.all(c["kp"] == 0) for c in robot.commands[-5:])


def test_after_the_episode_it_stands_until_ctrl_c(export):
    meta = json.loads((export / "policy.json").read_text())
    robot = FakeRobot(meta, follow=True)
    robot.set_q(np.asarray(meta["default_joint_pos"]))

    def on_tick(controller):
        if controller.report.phases and controller.report.phases[-1] >= 1 and controller.mode.value == "stand":
            if controller.tick - controller.mode_since >= 15:
                raise KeyboardInterrupt
        assert controller.tick < 200, "the episode did not end"

    report = _controller(export, robot, go=lambda: True, on_tick=on_tick,
                         safety=SafetyConfig(damping_s=0.0, ramp_s=0.1, stand_s=0.0, hold_after_s=None)).run()
    assert report.end == "interrupted" and report.phases[-1] >= 1
    stand = [c for c in robot.commands if c["kp"][0] > 0][-10:]  # the balance policy holds the robot
    assert all(np.allclose(c["q"], _stance29(export, robot.motors), atol=1e-5) for c in stand)
    assert all(np.all(c["kp"] == 0) for c in robot.commands[-5:])


def test_an_export_without_its_balance_policy_is_refused_before_anything_is_sent(export, tmp_path):
    bare = tmp_path / "bare"
    shutil.copytree(export, bare)
    (bare / "chain.json").unlink()
    robot = FakeRobot(json.loads((bare / "policy.json").read_text()))
    with pytest.raises(PipelineInputError, match="no balance policy"):
        _controller(bare, robot)
    assert robot.commands == []


def test_the_go_counts_only_after_stand_s_of_balance(export):
    meta = json.loads((export / "policy.json").read_text())
    robot = FakeRobot(meta, follow=True)
    report = _controller(export, robot, go=lambda: True, on_tick=_stop_after(40),
                         safety=SafetyConfig(damping_s=0.04, ramp_s=0.1, stand_s=0.3)).run()
    modes = dict((name, tick) for tick, name in report.modes if name != "damping")
    assert modes["policy"] - modes["stand"] == 15  # 0.3 s at 50 Hz


def test_policy_needing_odometry_without_a_source_is_refused(export):
    with pytest.raises(PipelineInputError, match="observation.terms.*odometry"):
        G1Controller(export, 1.4, state_reader=None, cmd_writer=None, sdk=SDK, pose_source=None)


def test_deploy_cli_needs_an_interface(export, capsys):
    from pipeline.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["deploy", str(export), "--psi", "1.4"])
    assert exit_.value.code == 2 and "--interface" in capsys.readouterr().err


def test_key_go_counts_only_an_enter_pressed_once_armed():
    import io

    from pipeline.deploy.controller import KeyGo

    read, write = os.pipe()
    go = KeyGo(io.TextIOWrapper(os.fdopen(read, "rb")))
    os.write(write, b"\n")  # pressed during the ramp: discarded
    time.sleep(0.1)
    go.arm()
    time.sleep(0.05)
    assert not go()
    os.write(write, b"\n")
    _wait(go)
    os.close(write)


def test_odometry_from_a_topic_that_stops_reads_as_none(monkeypatch):
    """A frozen odometry node must not feed the policy a held position: past max_age_s the pose is gone,
    and Odometry.read raises, which the controller turns into damping."""
    from types import SimpleNamespace as NS

    from pipeline.deploy.odometry import Odometry, TopicPose

    half_turn = np.sqrt(0.5)  # 90° of yaw
    message = NS(pose=NS(pose=NS(position=NS(x=1.0, y=2.0, z=0.8),
                                 orientation=NS(w=half_turn, x=0.0, y=0.0, z=half_turn))))
    inbox = [[message]]
    reader = NS(take=lambda N: inbox.pop(0) if inbox else [])
    link = NS(reader=lambda topic, kind: reader, types=NS(Odometry=object))
    now = [100.0]
    monkeypatch.setattr(time, "monotonic", lambda: now[0])

    source = TopicPose(link, "rt/odometry", max_age_s=0.5)
    position, yaw = source.pose()
    np.testing.assert_allclose(position, [1.0, 2.0, 0.8])
    assert yaw == pytest.approx(np.pi / 2)
    odometry = Odometry(source)
    odometry.start()
    now[0] += 0.4
    np.testing.assert_allclose(odometry.read(), [0.0, 0.0, 0.0], atol=1e-12)  # still fresh
    now[0] += 0.2
    assert source.pose() is None
    with pytest.raises(RuntimeError, match="none fresh"):
        odometry.read()
