"""The CRC the G1 checks on `unitree_hg` LowCmd_ and puts on LowState_.

The robot packs the message as its C struct (little-endian, 4-byte aligned), reads it as 32-bit
words, drops the last (the crc field itself) and runs CRC-32 with polynomial 0x04C11DB7, initial
value 0xFFFFFFFF, most significant bit first, no final xor (CRC-32/MPEG-2 over each word's bytes
taken big-end first). The SDK computes it bit by bit in Python or through a bundled shared library
that the PyPI wheel (unitree-sdk2 1.0.1) does not ship; here it runs through zlib's CRC-32 via the
bit-reflection identity, ~10 µs per message. tests/test_deploy.py checks it against the SDK's own
bitwise implementation.
"""

from __future__ import annotations

import struct
import zlib

# struct layouts of unitree_hg LowCmd_ (1004 bytes) and LowState_ (2092 bytes), crc field last
LOW_CMD_FORMAT = struct.Struct("<2B2x" + "B3x5fI" * 35 + "5I")
LOW_STATE_FORMAT = struct.Struct("<2I2B2xI" + "13fh2x" + "B3x4f2hf7I" * 35 + "40B5I")

_REVERSE_BITS = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))


def _reverse32(value: int) -> int:
    return int(f"{value:032b}"[::-1], 2)


def crc32_words(packed: bytes) -> int:
    """The robot's CRC over the little-endian 32-bit words of `packed`, its last word excluded."""
    n = len(packed) // 4 - 1
    words = struct.unpack_from(f"<{n}I", packed)
    big_endian = struct.pack(f">{n}I", *words)
    # MSB-first CRC == bit-reversed reflected CRC over bit-reversed bytes (zlib: init and xorout ~0)
    return _reverse32(~zlib.crc32(big_endian.translate(_REVERSE_BITS)) & 0xFFFFFFFF)


def pack_low_cmd(cmd) -> bytes:
    values = [cmd.mode_pr, cmd.mode_machine]
    for m in cmd.motor_cmd:
        values += [m.mode, m.q, m.dq, m.tau, m.kp, m.kd, m.reserve]
    values += [*cmd.reserve, cmd.crc]
    return LOW_CMD_FORMAT.pack(*values)


def pack_low_state(state) -> bytes:
    imu = state.imu_state
    values = [*state.version, state.mode_pr, state.mode_machine, state.tick, *imu.quaternion, *imu.gyroscope,
              *imu.accelerometer, *imu.rpy, imu.temperature]
    for m in state.motor_state:
        values += [m.mode, m.q, m.dq, m.ddq, m.tau_est, *m.temperature, m.vol, *m.sensor, m.motorstate, *m.reserve]
    values += [*state.wireless_remote, *state.reserve, state.crc]
    return LOW_STATE_FORMAT.pack(*values)


def low_cmd_crc(cmd) -> int:
    return crc32_words(pack_low_cmd(cmd))


def low_state_crc(state) -> int:
    return crc32_words(pack_low_state(state))
