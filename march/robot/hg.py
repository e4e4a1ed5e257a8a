"""Unitree's ``hg`` low-level messages (G1, H1-2) as cyclonedds IDL types, written in the project.

From the robot's published layout (unitree_sdk2 ``idl/hg``; the same type names go on the wire,
so a real G1 and these types interoperate): ``LowCmd_`` = mode_pr, mode_machine,
motor_cmd[35] (mode, q, dq, tau, kp, kd, reserve), reserve[4], crc; ``LowState_`` = version[2],
mode_pr, mode_machine, tick, imu_state (quaternion w x y z, gyroscope, accelerometer, rpy,
temperature), motor_state[35] (mode, q, dq, ddq, tau_est, temperature[2], vol, sensor[2],
motorstate, reserve[4]), wireless_remote[40], reserve[4], crc. No vendor SDK is needed.

The CRC is Unitree's: the message packed as its C struct (little-endian, natural alignment:
``LowCmd_`` 1004 bytes, ``LowState_`` 2092 bytes), read as 32-bit words, all but the last (the
crc itself) fed MSB-first to a CRC-32 with polynomial 0x04C11DB7, initial value 0xFFFFFFFF, no
reflection and no final xor (unitree_sdk2 ``crc32_core``) - i.e. CRC-32/MPEG-2 over each word's
big-endian bytes. A robot drops a LowCmd whose crc is wrong.

(No ``from __future__ import annotations`` here: cyclonedds reads the field annotations as
objects.)
"""

import struct
import zlib
from dataclasses import dataclass, field

from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t

NUM_MOTORS = 35
LOWCMD_TYPE = "unitree_hg::msg::dds_::LowCmd_"
LOWSTATE_TYPE = "unitree_hg::msg::dds_::LowState_"


@dataclass
class MotorCmd_(IdlStruct, typename="unitree_hg::msg::dds_::MotorCmd_"):
    mode: t.uint8 = 0
    q: t.float32 = 0.0
    dq: t.float32 = 0.0
    tau: t.float32 = 0.0
    kp: t.float32 = 0.0
    kd: t.float32 = 0.0
    reserve: t.uint32 = 0


@dataclass
class LowCmd_(IdlStruct, typename=LOWCMD_TYPE):
    mode_pr: t.uint8 = 0
    mode_machine: t.uint8 = 0
    motor_cmd: t.array[MotorCmd_, NUM_MOTORS] = field(
        default_factory=lambda: [MotorCmd_() for _ in range(NUM_MOTORS)]
    )
    reserve: t.array[t.uint32, 4] = field(default_factory=lambda: [0, 0, 0, 0])
    crc: t.uint32 = 0


@dataclass
class IMUState_(IdlStruct, typename="unitree_hg::msg::dds_::IMUState_"):
    quaternion: t.array[t.float32, 4] = field(default_factory=lambda: [1.0, 0.0, 0.0, 0.0])
    gyroscope: t.array[t.float32, 3] = field(default_factory=lambda: [0.0] * 3)
    accelerometer: t.array[t.float32, 3] = field(default_factory=lambda: [0.0] * 3)
    rpy: t.array[t.float32, 3] = field(default_factory=lambda: [0.0] * 3)
    temperature: t.int16 = 0


@dataclass
class MotorState_(IdlStruct, typename="unitree_hg::msg::dds_::MotorState_"):
    mode: t.uint8 = 0
    q: t.float32 = 0.0
    dq: t.float32 = 0.0
    ddq: t.float32 = 0.0
    tau_est: t.float32 = 0.0
    temperature: t.array[t.int16, 2] = field(default_factory=lambda: [0, 0])
    vol: t.float32 = 0.0
    sensor: t.array[t.uint32, 2] = field(default_factory=lambda: [0, 0])
    motorstate: t.uint32 = 0
    reserve: t.array[t.uint32, 4] = field(default_factory=lambda: [0, 0, 0, 0])


@dataclass
class LowState_(IdlStruct, typename=LOWSTATE_TYPE):
    version: t.array[t.uint32, 2] = field(default_factory=lambda: [0, 0])
    mode_pr: t.uint8 = 0
    mode_machine: t.uint8 = 0
    tick: t.uint32 = 0
    imu_state: IMUState_ = field(default_factory=IMUState_)
    motor_state: t.array[MotorState_, NUM_MOTORS] = field(
        default_factory=lambda: [MotorState_() for _ in range(NUM_MOTORS)]
    )
    wireless_remote: t.array[t.uint8, 40] = field(default_factory=lambda: [0] * 40)
    reserve: t.array[t.uint32, 4] = field(default_factory=lambda: [0, 0, 0, 0])
    crc: t.uint32 = 0


# ---------------------------------------------------------------------------------------------
# CRC as Unitree computes it.

LOWCMD_FORMAT = "<2B2x" + "B3x5fI" * NUM_MOTORS + "5I"
LOWSTATE_FORMAT = "<2I2B2xI" + "13fh2x" + "B3x4f2hf7I" * NUM_MOTORS + "40B5I"
POLY = 0x04C11DB7


def _table() -> list[int]:
    out = []
    for byte in range(256):
        c = byte << 24
        for _ in range(8):
            c = ((c << 1) ^ POLY) if c & 0x80000000 else (c << 1)
        out.append(c & 0xFFFFFFFF)
    return out


TABLE = _table()


def crc32_words_slow(words) -> int:
    """Unitree's ``crc32_core`` over 32-bit words, table-driven byte by byte (the reference)."""
    crc = 0xFFFFFFFF
    data = struct.pack(f">{len(words)}I", *(int(w) & 0xFFFFFFFF for w in words))
    for b in data:
        crc = ((crc << 8) & 0xFFFFFFFF) ^ TABLE[((crc >> 24) ^ b) & 0xFF]
    return crc


BIT_REVERSED = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))


def crc32_words(words) -> int:
    """The same CRC through zlib (C): CRC-32/MPEG-2 is zlib's reflected CRC-32 of the
    bit-reversed bytes, bit-reversed, without its final xor (~1 ms -> ~20 us a LowState: the
    loop checks every LowState it uses, the supervisor every message it watches)."""
    data = struct.pack(f">{len(words)}I", *(int(w) & 0xFFFFFFFF for w in words))
    r = zlib.crc32(data.translate(BIT_REVERSED)) ^ 0xFFFFFFFF
    return int(f"{r:032b}"[::-1], 2)


def pack_lowcmd(cmd: LowCmd_) -> bytes:
    values: list = [cmd.mode_pr, cmd.mode_machine]
    for m in cmd.motor_cmd:
        values += [m.mode, m.q, m.dq, m.tau, m.kp, m.kd, m.reserve]
    values += [*cmd.reserve, cmd.crc]
    return struct.pack(LOWCMD_FORMAT, *values)


def pack_lowstate(s: LowState_) -> bytes:
    imu = s.imu_state
    values: list = [*s.version, s.mode_pr, s.mode_machine, s.tick]
    values += [*imu.quaternion, *imu.gyroscope, *imu.accelerometer, *imu.rpy, imu.temperature]
    for m in s.motor_state:
        values += [m.mode, m.q, m.dq, m.ddq, m.tau_est, *m.temperature, m.vol, *m.sensor]
        values += [m.motorstate, *m.reserve]
    values += [*s.wireless_remote, *s.reserve, s.crc]
    return struct.pack(LOWSTATE_FORMAT, *values)


def crc_of(packed: bytes) -> int:
    """The crc of a packed message: over every word but the last (the crc field)."""
    body = packed[:-4]  # every word but the crc, each little-endian: fed MSB-first
    data = bytearray(len(body))
    data[0::4], data[1::4], data[2::4], data[3::4] = body[3::4], body[2::4], body[1::4], body[0::4]
    r = zlib.crc32(bytes(data).translate(BIT_REVERSED)) ^ 0xFFFFFFFF
    return int(f"{r:032b}"[::-1], 2)


def lowcmd_crc(cmd: LowCmd_) -> int:
    return crc_of(pack_lowcmd(cmd))


def lowstate_crc(s: LowState_) -> int:
    return crc_of(pack_lowstate(s))
