"""StreamOutput.set_interval / request_message (the functions the COMMAND_LONG router calls for
MAV_CMD_SET_MESSAGE_INTERVAL and MAV_CMD_REQUEST_MESSAGE) and AUTOPILOT_VERSION's encoding,
with pymavlink as the GCS peer on loopback, stepped in simulated time."""
from __future__ import annotations

import math
import subprocess
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav
from tests.mavlink_peer import Link, of_type

from vehicles.mavlink.endpoint.streams import flight_custom_version

pytestmark = pytest.mark.live

ATT = mav.MAVLINK_MSG_ID_ATTITUDE


def test_set_interval_rates_measured_in_simulated_time():
    with Link() as L:
        assert L.ep.set_interval(ATT, 250_000) == mav.MAV_RESULT_ACCEPTED  # MAVProxy's 4 Hz
        got = L.step(100)  # 10 s at 10 Hz steps
        assert abs(len(of_type(got, "ATTITUDE")) - 40) <= 1
        assert L.ep.set_interval(ATT, 100_000) == mav.MAV_RESULT_ACCEPTED
        assert abs(len(of_type(L.step(100), "ATTITUDE")) - 100) <= 1


def test_set_interval_clamped_to_the_epoch():
    with Link() as L:
        # 50 Hz asked: one per vehicle epoch (0.1 s here), never more than one a step
        assert L.ep.set_interval(ATT, 20_000) == mav.MAV_RESULT_ACCEPTED
        assert L.ep._interval[ATT] == pytest.approx(0.1)
        assert abs(len(of_type(L.step(50), "ATTITUDE")) - 50) <= 1
        L.ep.epoch_s = 0.05  # a scenario at 20 Hz
        assert L.ep.set_interval(ATT, 20_000) == mav.MAV_RESULT_ACCEPTED
        assert L.ep._interval[ATT] == pytest.approx(0.05)


@pytest.mark.parametrize("msgid, iv, result", [
    (ATT, math.nan, mav.MAV_RESULT_DENIED), (ATT, -5, mav.MAV_RESULT_DENIED), (ATT, math.inf, mav.MAV_RESULT_DENIED),
    (ATT, "x", mav.MAV_RESULT_DENIED), (397, 100_000, mav.MAV_RESULT_UNSUPPORTED),
    (math.nan, 100_000, mav.MAV_RESULT_UNSUPPORTED), (None, 1, mav.MAV_RESULT_DENIED)])
def test_set_interval_bad_input_clear_result_counted_never_raises(msgid, iv, result):
    with Link() as L:
        before = dict(L.ep._interval)
        assert L.ep.set_interval(msgid, iv) == result
        assert L.ep._interval == before  # nothing changed
        key = "cmd_unsupported" if result == mav.MAV_RESULT_UNSUPPORTED else "interval_bad"
        assert L.ep.counters.get(key) == 1


def test_set_interval_stop_and_default():
    with Link() as L:
        assert L.ep.set_interval(ATT, -1) == mav.MAV_RESULT_ACCEPTED
        assert not of_type(L.step(30), "ATTITUDE")
        assert L.ep.set_interval(ATT, 0) == mav.MAV_RESULT_ACCEPTED  # default 4 Hz
        assert abs(len(of_type(L.step(50), "ATTITUDE")) - 20) <= 1


def test_request_message_sends_at_once_or_says_why_not():
    with Link() as L:
        L.step(1)
        assert L.ep.request_message(mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION, L.peer.addr) == mav.MAV_RESULT_ACCEPTED
        assert of_type(L.peer.drain(0.5), "AUTOPILOT_VERSION")
        assert L.ep.request_message(397) == mav.MAV_RESULT_UNSUPPORTED
        assert L.ep.request_message(math.nan) == mav.MAV_RESULT_UNSUPPORTED
        assert L.ep.counters["cmd_unsupported"] == 2
    with Link(tel=None) as L:
        L.tel = None
        L.step(1)
        assert L.ep.request_message(ATT) == mav.MAV_RESULT_TEMPORARILY_REJECTED


def test_autopilot_version_custom_version_is_the_git_hash():
    with Link() as L:
        L.step(1)
        L.ep.request_message(mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION, L.peer.addr)
        v = of_type(L.peer.drain(0.5), "AUTOPILOT_VERSION")[0]
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                          text=True).stdout.strip()
    assert bytes(v.flight_custom_version).hex() == head[:16] == bytes(flight_custom_version()).hex()
    # flight_sw_version: major << 24 | minor << 16 | patch << 8 | FIRMWARE_VERSION_TYPE (ArduPilot's packing)
    assert v.flight_sw_version & 0xFF in (mav.FIRMWARE_VERSION_TYPE_DEV, mav.FIRMWARE_VERSION_TYPE_OFFICIAL)
