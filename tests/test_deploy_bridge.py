"""G1 deployment over DDS on the loopback interface (a random domain per test) against the MuJoCo sim bridge:
the gantry, the chain, `rehearse` with the real timings, a killed bridge, and the dry run."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np

from pipeline.deploy.crc import low_state_crc
from pipeline.deploy.motors import NUM_MOTORS
from pipeline.deploy.safety import SafetyConfig

from deploy_helpers import REPO, SDK, FakeRobot, _domain, _stop_after, export, standing_export  # noqa: F401  (export, standing_export: module fixtures)


# ------------------------------------------------------------------------------ over DDS with the sim bridge
def _bridge(export, domain, *extra):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", "pipeline.cli", "sim-bridge", str(export), "--psi", "1.4",
                             "--interface", "lo", "--domain", str(domain), *extra], env=env, cwd=REPO,
                            stderr=subprocess.PIPE, text=True)


def test_on_the_bridge_the_robot_is_lowered_from_its_gantry_and_runs_the_chain(standing_export, tmp_path):
    """Lockstep bridge at 500 Hz physics and motor law: the G1 hangs in the default pose at the task's
    start, is lowered onto its feet, and deploy runs damping, ramp, the balance policy, the task to its
    handoff and the balance policy again, never from the policy's trained state."""
    from pipeline.deploy.controller import run_deploy

    domain, trace = _domain(), tmp_path / "trace.npz"
    bridge = _bridge(standing_export, domain, "--lockstep", "--trace", str(trace), "--gantry-s", "0.6")
    try:
        report = run_deploy(standing_export, 1.4, interface="lo", domain_id=domain, go_flag=True, lockstep=True,
                            odometry_topic="rt/adamimic/odometry",
                            safety=SafetyConfig(damping_s=0.2, ramp_s=0.4, stand_s=0.4, hold_after_s=0.2))
    finally:
        bridge.send_signal(signal.SIGTERM)
        bridge.wait(timeout=20)
    assert report.end == "done", report.message
    assert [m for _, m in report.modes] == ["damping", "ramp", "stand", "policy", "stand", "damping"]
    assert report.phases[-1] >= 1.0 - 1e-6
    run = np.load(trace)
    meta = json.loads((standing_export / "policy.json").read_text())
    first = run["qpos"][0]
    assert np.allclose(first[:2], meta["initial_state"]["qpos"][:2], atol=0.02)  # at the task's start ...
    assert first[2] > 0.76 + 0.03  # ... hanging above the stance
    assert not np.allclose(first, meta["initial_state"]["qpos"][:7], atol=0.02)  # not the trained state


def test_rehearse_runs_deploy_against_the_bridge_with_the_real_timings(standing_export):
    """`adamimic rehearse`: real time, deploy's default damping (1 s), ramp (3 s), 2 s of standing, the
    go, the task, then the balance policy; one JSON line per ψ with the chain's verdicts."""
    from pipeline.deploy.rehearse import rehearse

    start = time.monotonic()
    (line,) = rehearse(standing_export, [1.4], keep_s=3.5, log=lambda _: None)
    defaults = SafetyConfig()
    assert time.monotonic() - start >= defaults.damping_s + defaults.ramp_s + defaults.stand_s
    assert line["modes"][:4] == ["damping", "ramp", "stand", "policy"] and line["modes"][-1] == "damping"
    assert abs(line["stood_before_go_s"] - defaults.stand_s) < 0.05
    assert set(line) >= {"psi", "keyframe_errors", "success", "standing", "rest_to_rest", "joint_past_limit_rad"}
    assert line["rest_to_rest"] == (line["success"] and line["standing"])
    if line["deploy_end"] == "done":  # handed over and held for keep_s: the balance policy came back
        assert line["modes"][4] == "stand" and time.monotonic() - start >= 6.0 + 3.5
    else:  # the stand-in policies may let the robot fall: the watchdog's damping, and no rest_to_rest
        assert line["deploy_end"] == "fault" and not line["rest_to_rest"]


def test_killed_bridge_mid_episode_sends_the_controller_to_damping(export):
    from pipeline.deploy.controller import run_deploy

    domain = _domain()
    bridge = _bridge(export, domain)  # real time, like the robot
    killed_at = []

    def kill_mid_episode(controller):
        if len(controller.report.phases) == 5 and not killed_at:
            bridge.send_signal(signal.SIGKILL)
            killed_at.append(time.monotonic())
        assert controller.tick < 500, "the controller never noticed"

    try:
        report = run_deploy(export, 1.4, interface="lo", domain_id=domain, go_flag=True,
                            odometry_topic="rt/adamimic/odometry", on_tick=kill_mid_episode,
                            safety=SafetyConfig(damping_s=0.1, ramp_s=0.2, stand_s=0.1, hold_after_s=0.1,
                                                state_timeout_s=0.3, first_state_timeout_s=20))
    finally:
        bridge.kill()
        bridge.wait(timeout=20)
    assert killed_at, report.message
    assert report.end == "fault" and "LowState stopped" in report.message and report.exit_code == 3
    assert report.modes[-1][1] == "damping" and report.last_kp == [0.0] * NUM_MOTORS
    assert time.monotonic() - killed_at[0] < 2.0


def test_dry_run_publishes_nothing(export):
    from pipeline.deploy.controller import run_deploy
    from pipeline.deploy.transport import LOW_CMD_TOPIC, LOW_STATE_TOPIC, DdsLink

    domain = _domain()
    link = DdsLink(domain, "lo")
    state_writer = link.writer(LOW_STATE_TOPIC, SDK.LowState)
    commands = link.reader(LOW_CMD_TOPIC, SDK.LowCmd, keep_last=100)
    meta = json.loads((export / "policy.json").read_text())
    robot = FakeRobot(meta)
    robot.set_q(np.asarray(meta["default_joint_pos"]))
    stop = threading.Event()

    def publish_states():  # a robot standing still, 100 Hz
        while not stop.is_set():
            robot.state.tick += 10
            robot.state.crc = low_state_crc(robot.state)
            state_writer.write(robot.state)
            time.sleep(0.01)

    thread = threading.Thread(target=publish_states, daemon=True)
    thread.start()
    try:
        report = run_deploy(export, 1.4, interface="lo", domain_id=domain, dry_run=True, go_flag=True,
                            pose=lambda: (np.zeros(3), 0.0), on_tick=_stop_after(14),
                            safety=SafetyConfig(damping_s=0.04, ramp_s=0.1, stand_s=0.04, state_timeout_s=0.5))
    finally:
        stop.set()
        thread.join()
    assert len(report.phases) >= 3 and report.commands_written > 0 and "none published" in report.message
    time.sleep(0.2)
    assert commands.take(N=100) == []
