"""`adamimic deploy`: the exported chain on a G1 over its low-level DDS interface, at 50 Hz.

Each tick takes the newest sound LowState (CRC and motor count checked), lets the watchdog judge
it, and publishes one signed LowCmd: per motor q, dq = 0, kp, kd, tau = 0 for the robot's 500 Hz
PD. After the damping and the ramp to the default pose, the export's balance policy holds the robot
(STAND); on the go the task policy runs (POLICY) until its phase reaches the chain's handoff, and the
balance policy takes the robot back (STAND) until Ctrl-C. Both policies' observations, phase and
odometry hold come from `PolicyStepper`, the same code `sim2sim` runs, and its joint targets go out
unchanged, as in training and `sim2sim` (only the ramp's are clamped to the joints' ranges); nothing
but the export (policy.onnx + policy.json, balance/, chain.json) describes them.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.deploy.crc import low_cmd_crc
from pipeline.deploy.motors import NUM_MOTORS, MotorMap
from pipeline.deploy.odometry import Odometry, require_odometry
from pipeline.deploy.safety import Measured, Mode, SafetyConfig, Watchdog, clamp_targets, ramp_targets
from pipeline.export.policy_step import PolicyStepper, projected_gravity

EXIT_DAMPING_TICKS = 5  # damping commands sent before leaving, so damping is the last word on the wire


@dataclass
class DeployReport:
    end: str  # "done", "max_steps", "fault", "interrupted", "no_state"
    message: str
    modes: list[tuple[int, str]] = field(default_factory=list)  # (tick, mode entered)
    phases: list[float] = field(default_factory=list)  # phase after each policy step
    state_ticks: list[int] = field(default_factory=list)  # LowState tick each policy step acted on
    step_latency_s: list[float] = field(default_factory=list)  # policy ticks: state taken → command written
    refused_states: int = 0
    commands_written: int = 0
    last_kp: list[float] = field(default_factory=list)  # gains of the last command written (29 motors)
    joint_past_limit_rad: float = 0.0  # the furthest any measured joint went past its range

    @property
    def exit_code(self) -> int:
        return {"done": 0, "max_steps": 0, "interrupted": 0}.get(self.end, 3)


class KeyGo:
    """The go: Enter on the terminal, counted only once armed (standing in the default pose), read on
    a thread so the loop never blocks. An Enter pressed earlier is discarded, not remembered."""

    def __init__(self, stream=None):
        self.event = threading.Event()
        self.armed = False
        self.stream = stream or sys.stdin
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for _ in self.stream:
            if self.armed:
                self.event.set()
                return

    def arm(self) -> None:
        if not self.armed:
            print("deploy: the balance policy holds the robot; press Enter for the go (Ctrl-C: damping)",
                  file=sys.stderr, flush=True)
        self.armed = True

    def __call__(self) -> bool:
        return self.event.is_set()


def load_joint_limits(meta: dict, joint_names) -> np.ndarray:
    """(J, 2) limits: the export's `joint_limits` when present, else the G1 model the policy was
    trained on (the vendored MJCF)."""
    if "joint_limits" in meta:
        return np.asarray(meta["joint_limits"], dtype=np.float64)
    from pipeline.robot.g1 import build_model, joint_limits

    return joint_limits(build_model(), tuple(joint_names))


class G1Controller:
    def __init__(self, export_dir: str | Path, psi: float, *, state_reader, cmd_writer, sdk,
                 safety: SafetyConfig = SafetyConfig(), go: Callable[[], bool] = lambda: True,
                 pose_source=None, lockstep: bool = False, on_tick: Callable[["G1Controller"], None] | None = None,
                 log: Callable[[str], None] = lambda line: print(line, file=sys.stderr, flush=True)):
        from pipeline.export.sim2sim import check_psi, load_exported

        from pipeline.export.chain import read_chain

        self.chain = read_chain(export_dir)  # no balance policy: refused before anything is sent
        session, self.meta = load_exported(export_dir)
        check_psi(self.meta, psi)
        self.psi = float(psi)
        self.stepper = PolicyStepper(session, self.meta)
        balance_session, balance_meta = load_exported(Path(export_dir) / self.chain["balance"])
        if balance_meta["joint_names"] != self.meta["joint_names"]:
            raise PipelineInputError(Path(export_dir) / self.chain["balance"] / "policy.json", "joint_names",
                                     "differ from the task policy's")
        self.balance = PolicyStepper(balance_session, balance_meta)
        self.handoff_phase = float(self.chain["handoff_phase"])
        self.motors = MotorMap.from_joint_names(self.meta["joint_names"], str(Path(export_dir) / "policy.json"))
        self.odometry: Odometry | None = require_odometry(self.stepper.needs_odometry, pose_source,
                                                          str(Path(export_dir) / "policy.json"))
        self.default = np.asarray(self.meta["default_joint_pos"], dtype=np.float64)
        self.kp = np.asarray(self.meta["kp"], dtype=np.float64)
        self.kd = np.asarray(self.meta["kd"], dtype=np.float64)
        self.limits = load_joint_limits(self.meta, self.meta["joint_names"])
        self.safety = safety
        self.watchdog = Watchdog(safety, self.limits, self.meta["joint_names"])
        self.state_reader, self.cmd_writer, self.sdk = state_reader, cmd_writer, sdk
        self.go, self.lockstep, self.on_tick, self.log = go, lockstep, on_tick, log
        self.dt = float(self.meta["control_dt"])
        self.max_policy_steps = self.stepper.max_steps  # as sim2sim
        self.cmd = sdk.new_low_cmd()
        self.mode = Mode.DAMPING
        self.tick = 0
        self.report = DeployReport("running", "")

    # ---------------------------------------------------------------------- commands
    def _write(self, q: np.ndarray, kp: np.ndarray, kd: np.ndarray, mode_machine: int) -> None:
        """Joint-order targets and gains → one signed LowCmd; the locked motors held at 0."""
        m = self.motors
        q29 = m.to_motors(q, 0.0)
        kp29 = m.to_motors(kp, kp[m.locked_gain_joint])
        kd29 = m.to_motors(kd, kd[m.locked_gain_joint])
        cmd = self.cmd
        cmd.mode_pr = 0  # ankles in pitch/roll mode, as the policy's joints are
        cmd.mode_machine = int(mode_machine)
        for i, motor in enumerate(cmd.motor_cmd):
            if i < NUM_MOTORS:
                motor.mode, motor.q, motor.dq, motor.tau = 1, float(q29[i]), 0.0, 0.0
                motor.kp, motor.kd = float(kp29[i]), float(kd29[i])
            else:
                motor.mode, motor.q, motor.dq, motor.tau, motor.kp, motor.kd = 0, 0.0, 0.0, 0.0, 0.0, 0.0
        cmd.crc = low_cmd_crc(cmd)
        self.cmd_writer.write(cmd)
        self.report.commands_written += 1
        self.report.last_kp = kp29.tolist()

    def _damping(self, measured_q: np.ndarray, mode_machine: int) -> None:
        self._write(measured_q, np.zeros_like(self.kp), self.kd * self.safety.damping_kd_scale, mode_machine)

    # ---------------------------------------------------------------------- state
    def _take_state(self, last_tick: int | None):
        """Newest sound LowState; in lockstep (a stepped simulator) wait for the one after our command."""
        received = self.state_reader.poll()
        if self.lockstep and received is not None and last_tick is not None:
            deadline = time.monotonic() + self.safety.state_timeout_s
            while received.message.tick <= last_tick and time.monotonic() < deadline:
                time.sleep(0.0002)
                received = self.state_reader.poll()
        return received

    def _measure(self, received, now: float) -> Measured:
        s = received.message
        q = np.array([s.motor_state[i].q for i in self.motors.motor_of_joint], dtype=np.float64)
        dq = np.array([s.motor_state[i].dq for i in self.motors.motor_of_joint], dtype=np.float64)
        return Measured(q, dq, projected_gravity(s.imu_state.quaternion),
                        np.asarray(s.imu_state.gyroscope, dtype=np.float64), now - received.time)

    def _elapsed(self) -> float:
        return (self.tick - self.mode_since) * self.dt

    def _enter(self, mode: Mode) -> None:
        self.mode = mode
        self.mode_since = self.tick
        self.report.modes.append((self.tick, mode.value))
        self.log(f"deploy: {mode.value}")

    # ---------------------------------------------------------------------- loop
    def run(self) -> DeployReport:
        start = time.monotonic()
        next_tick = start
        last_tick: int | None = None
        last_q = self.default.copy()
        mode_machine = 0
        ramp_from = self.default.copy()
        finishing: str | None = None  # end reason once the episode is over (STAND → exit)
        try:
            self._enter(Mode.DAMPING)
            while True:
                t0 = time.monotonic()
                received = self._take_state(last_tick)
                self.report.refused_states = self.state_reader.refused
                if received is None:
                    if t0 - start > self.safety.first_state_timeout_s:
                        return self._finish("no_state", f"no sound LowState within "
                                            f"{self.safety.first_state_timeout_s} s (check the network "
                                            f"interface and that the robot is in low-level mode)", None, 0)
                    next_tick = self._sleep(next_tick)
                    continue
                measured = self._measure(received, time.monotonic())
                last_tick, last_q = int(received.message.tick), measured.joint_pos
                mode_machine = int(received.message.mode_machine)
                self.report.joint_past_limit_rad = max(self.report.joint_past_limit_rad,
                                                       self.watchdog.past_limit(measured.joint_pos))
                fault = self.watchdog.fault(measured)
                if fault is not None:
                    return self._finish("fault", fault, last_q, mode_machine)
                # modes whose time is over give way first, so a zero-length mode takes no tick
                if self.mode is Mode.DAMPING and self._elapsed() >= self.safety.damping_s:
                    ramp_from = measured.joint_pos.copy()
                    self._enter(Mode.RAMP)
                if self.mode is Mode.RAMP and self._elapsed() >= self.safety.ramp_s:
                    self._enter(Mode.STAND)
                    self.balance.reset()
                hold_after = self.safety.hold_after_s
                if (self.mode is Mode.STAND and finishing is not None and hold_after is not None
                        and self._elapsed() >= hold_after):
                    return self._finish(finishing, f"episode over ({finishing}), "
                                        f"{len(self.report.phases)} policy steps", last_q, mode_machine)
                if self.mode is Mode.STAND and finishing is None and hasattr(self.go, "arm"):
                    self.go.arm()
                if self.mode is Mode.STAND and finishing is None and self._elapsed() >= self.safety.stand_s and self.go():
                    self.stepper.reset()
                    if self.odometry is not None:
                        self.odometry.start()
                    self._enter(Mode.POLICY)
                elapsed = self._elapsed()
                if self.mode is Mode.DAMPING:
                    self._damping(measured.joint_pos, mode_machine)
                elif self.mode is Mode.RAMP:
                    target = ramp_targets(ramp_from, self.default, elapsed, self.safety.ramp_s)
                    self._write(clamp_targets(target, self.limits), self.kp, self.kd, mode_machine)
                elif self.mode is Mode.STAND:  # the balance policy, before the go and after the task
                    out = self.balance.step(base_ang_vel=measured.base_ang_vel, projected_gravity=measured.gravity,
                                            joint_pos=measured.joint_pos, joint_vel=measured.joint_vel, psi=0.0)
                    self._write(out.joint_targets, self.kp, self.kd, mode_machine)
                elif self.mode is Mode.POLICY:
                    odometry = (self.odometry.read() if self.odometry is not None and self.stepper.odometry_due()
                                else None)
                    out = self.stepper.step(base_ang_vel=measured.base_ang_vel, projected_gravity=measured.gravity,
                                            joint_pos=measured.joint_pos, joint_vel=measured.joint_vel,
                                            psi=self.psi, odometry=odometry)
                    self._write(out.joint_targets, self.kp, self.kd, mode_machine)
                    self.report.step_latency_s.append(time.monotonic() - t0)
                    self.report.phases.append(out.phase)
                    self.report.state_ticks.append(last_tick)
                    over = ("done" if out.phase >= self.handoff_phase - 1e-6
                            else "max_steps" if self.stepper.steps >= self.max_policy_steps else None)
                    if over is not None:
                        finishing = over
                        self._enter(Mode.STAND)
                        self.balance.reset()
                        if self.safety.hold_after_s is None:
                            self.log(f"deploy: episode over ({over}); the balance policy holds the robot, "
                                     f"Ctrl-C for damping")
                self.tick += 1
                if self.on_tick is not None:
                    self.on_tick(self)
                next_tick = self._sleep(next_tick)
        except KeyboardInterrupt:
            return self._finish("interrupted", "Ctrl-C (or SIGTERM)", last_q, mode_machine)
        except RuntimeError as error:  # odometry missing at the go or mid-episode
            return self._finish("fault", str(error), last_q, mode_machine)

    def _sleep(self, next_tick: float) -> float:
        next_tick += self.dt
        delay = next_tick - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            next_tick = time.monotonic()  # late: do not try to catch up with a burst of ticks
        return next_tick

    def _finish(self, end: str, message: str, last_q, mode_machine: int) -> DeployReport:
        """Damping as the last commands, whatever the reason; then the report."""
        if last_q is not None:
            self.mode = Mode.DAMPING
            self.report.modes.append((self.tick, Mode.DAMPING.value))
            for _ in range(EXIT_DAMPING_TICKS):
                try:
                    self._damping(last_q, mode_machine)
                    time.sleep(self.dt / 5)
                except KeyboardInterrupt:  # a second Ctrl-C: keep sending damping
                    continue
        self.report.end, self.report.message = end, message
        self.log(f"deploy: {end}: {message}; damping sent, exiting")
        return self.report


def run_deploy(export_dir: str | Path, psi: float, *, interface: str, domain_id: int = 0, dry_run: bool = False,
               go_flag: bool = False, odometry_topic: str | None = None, lockstep: bool = False,
               pose=None, safety: SafetyConfig = SafetyConfig(), on_tick=None) -> DeployReport:
    """Connects to the robot (or the sim bridge) on `interface` and runs one episode. Odometry:
    `odometry_topic` (nav_msgs Odometry_) or `pose`, a callable returning (world position, yaw)."""
    from pipeline.deploy.odometry import TopicPose
    from pipeline.deploy.transport import (LOW_CMD_TOPIC, LOW_STATE_TOPIC, CheckedReader, DdsLink, NullWriter,
                                           check_low_state)

    link = DdsLink(domain_id, interface)
    reader = CheckedReader(link.reader(LOW_STATE_TOPIC, link.types.LowState), check_low_state)
    writer = NullWriter() if dry_run else link.writer(LOW_CMD_TOPIC, link.types.LowCmd)
    if odometry_topic:
        pose = TopicPose(link, odometry_topic)
    controller = G1Controller(export_dir, psi, state_reader=reader, cmd_writer=writer, sdk=link.types,
                              safety=safety, go=(lambda: True) if go_flag else KeyGo(), pose_source=pose,
                              lockstep=lockstep, on_tick=on_tick)
    import signal

    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None  # SIGTERM too ends in damping
    try:
        report = controller.run()
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    if dry_run:
        report.message += f" (dry run: {writer.withheld} commands built, none published)"
    return report


def _interrupt(*_) -> None:
    raise KeyboardInterrupt


def check_interface(interface: str | None) -> str:
    if not interface:
        raise PipelineInputError("deploy", "--interface", "name the network interface that reaches the robot "
                                 "(e.g. enp3s0; lo for the sim bridge)")
    return interface
