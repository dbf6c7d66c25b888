"""``[[driver]] every = n``: a driver slower than the loop is read and written on every n-th
tick, and its feedback's age is judged at its own rate; a CAN bus loaded above 100 % at the
driver's rate is refused by ``check`` with the figure and what to change."""

from __future__ import annotations

import pytest
from helpers import arm_raw, virtual_loop

from aiohal.config import parse_config
from aiohal.errors import ConfigError


@pytest.mark.asyncio
async def test_a_driver_with_every_3_is_cycled_on_every_third_tick_and_is_not_stale():
    raw = arm_raw(2)
    raw["driver"][0]["every"] = 3
    raw["loop"]["max_feedback_age"] = 2
    async with virtual_loop(raw) as loop:
        driver = loop.slots[0].driver
        reads, writes = driver.reads, driver.writes
        report = await loop.run(ticks=300)
        assert driver.reads - reads == pytest.approx(100, abs=1)
        assert driver.writes - writes == pytest.approx(100, abs=1)
        assert driver.view.every == 3
    # fresh every third tick: 2 ticks old at most, within max_feedback_age (2) x every (3)
    assert report["faults"] == [] and report["safety_level"] == "run"


@pytest.mark.asyncio
async def test_lost_feedback_of_a_slower_driver_is_stale_after_max_age_of_its_cycles():
    raw = arm_raw(2)
    raw["driver"][0].update(every=3, options={"faults": {"feedback_lost_at_tick": 10}})
    raw["loop"]["max_feedback_age"] = 2
    async with virtual_loop(raw) as loop:
        report = await loop.run(ticks=100)
    # lost feedback is still seen: 2 x 3 ticks after the last fresh read, not never
    stale = [f for f in report["faults"] if f["phase"] == "check"]
    assert stale and 10 + 6 <= stale[0]["tick"] <= 10 + 6 + 3


def six_drives(rate_hz: float, every: int = 1) -> dict:
    joints = [f"j{i}" for i in range(6)]
    return {
        "robot": {"name": "can_arm"},
        "loop": {"rate_hz": rate_hz},
        "joints": {j: {"position": [-1.0, 1.0], "velocity": 1.0} for j in joints},
        "driver": [{"type": "canopen", "name": "can", "joints": joints, "every": every, "options": {
            "interface": "virtual", "channel": "not-opened", "nodes": [
                {"node_id": i + 1, "joint": j} for i, j in enumerate(joints)]}}],
        "controller": {"type": "hold"},
    }


def test_check_refuses_six_drives_at_1khz_on_classic_can_and_says_what_to_change():
    with pytest.raises(ConfigError) as err:
        parse_config(six_drives(1000))
    text = str(err.value)
    # 6 RPDOs of 7 bytes (125 bits), SYNC (55), 6 TPDOs of 8 bytes (135): 1615 bits per ms
    assert "driver[0].every: the CAN bus would be 162 % loaded: 13 frames of 1615 bits per cycle" in text
    assert "every = 2" in text


def test_the_same_bus_at_every_2_passes():
    config = parse_config(six_drives(1000, every=2))
    assert config.drivers[0].every == 2


def test_the_load_counts_the_pdos_the_config_maps():
    raw = six_drives(1000)
    for node in raw["driver"][0]["options"]["nodes"]:  # 2-byte RPDO and 6-byte TPDO: 75 + 115 bits, and SYNC (55)
        node.update(rx_pdos={"0x1600": ["0x6040:0:16"]}, tx_pdos={"0x1A00": ["0x6041:0:16", "0x6064:0:32"]})
    with pytest.raises(ConfigError, match=r"would be 120 % loaded: 13 frames of 1195 bits"):
        parse_config(raw)
