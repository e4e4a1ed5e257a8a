"""The hg messages written in the project: sizes, the wire round trip, Unitree's CRC.

The CRC is checked three ways: the CRC-32/MPEG-2 check value of "123456789" (0x0376E6E7, the
catalogue's), the table-driven code against a transcription of unitree_sdk2's bit loop
(``crc32_core``) over generated messages, and a flipped bit in any field changes it.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from march.robot import hg


def crc32_core(words) -> int:
    """unitree_sdk2's crc32_core, transcribed bit by bit (the reference)."""
    crc = 0xFFFFFFFF
    for data in words:
        xbit = 1 << 31
        for _ in range(32):
            if crc & 0x80000000:
                crc = ((crc << 1) & 0xFFFFFFFF) ^ hg.POLY
            else:
                crc = (crc << 1) & 0xFFFFFFFF
            if data & xbit:
                crc ^= hg.POLY
            xbit >>= 1
    return crc


def test_crc_check_value():
    crc = 0xFFFFFFFF
    for b in b"123456789":
        crc = ((crc << 8) & 0xFFFFFFFF) ^ hg.TABLE[((crc >> 24) ^ b) & 0xFF]
    assert crc == 0x0376E6E7


def test_packed_sizes_are_the_c_structs():
    assert struct.calcsize(hg.LOWCMD_FORMAT) == 1004  # 2 + 2 pad + 35 x 28 + 5 x 4
    assert struct.calcsize(hg.LOWSTATE_FORMAT) == 2092
    assert len(hg.pack_lowcmd(hg.LowCmd_())) == 1004
    assert len(hg.pack_lowstate(hg.LowState_())) == 2092


def _random_cmd(rng) -> hg.LowCmd_:
    cmd = hg.LowCmd_(mode_pr=int(rng.integers(2)), mode_machine=int(rng.integers(256)))
    for m in cmd.motor_cmd:
        m.mode = int(rng.integers(2))
        m.q, m.dq, m.tau, m.kp, m.kd = (float(np.float32(v)) for v in rng.normal(size=5))
    return cmd


@pytest.mark.parametrize("seed", range(6))
def test_table_crc_equals_unitrees_bit_loop(seed):
    rng = np.random.default_rng(seed)
    cmd = _random_cmd(rng)
    words = struct.unpack("<251I", hg.pack_lowcmd(cmd))
    assert hg.lowcmd_crc(cmd) == crc32_core(words[:-1])
    ls = hg.LowState_(tick=int(rng.integers(2**32)))
    ls.imu_state.quaternion = [float(np.float32(v)) for v in rng.normal(size=4)]
    ls.motor_state[7].q = float(np.float32(rng.normal()))
    words = struct.unpack("<523I", hg.pack_lowstate(ls))
    assert hg.lowstate_crc(ls) == crc32_core(words[:-1])


def test_any_changed_field_changes_the_crc_and_the_wire_keeps_it():
    rng = np.random.default_rng(9)
    cmd = _random_cmd(rng)
    cmd.crc = hg.lowcmd_crc(cmd)
    back = hg.LowCmd_.deserialize(cmd.serialize())
    assert back.crc == cmd.crc == hg.lowcmd_crc(back)
    for slot in (0, 17, 34):
        changed = hg.LowCmd_.deserialize(cmd.serialize())
        changed.motor_cmd[slot].kp += 1.0
        assert hg.lowcmd_crc(changed) != cmd.crc
    changed = hg.LowCmd_.deserialize(cmd.serialize())
    changed.mode_machine ^= 1
    assert hg.lowcmd_crc(changed) != cmd.crc
    ls = hg.LowState_(tick=5)
    ls.crc = hg.lowstate_crc(ls)
    assert hg.LowState_.deserialize(ls.serialize()).crc == ls.crc


def test_type_names_are_unitrees():
    assert hg.LOWCMD_TYPE == "unitree_hg::msg::dds_::LowCmd_"
    assert hg.LOWSTATE_TYPE == "unitree_hg::msg::dds_::LowState_"
    assert len(hg.LowCmd_().motor_cmd) == len(hg.LowState_().motor_state) == 35
