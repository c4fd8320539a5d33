"""The modem readers (onboard/modem.py): ModemManager's JSON as mmcli prints it, the emulated cell's
report, and the poller's thread (a fake read: the real sources need a modem or a cell)."""

from __future__ import annotations

import json
import threading
import time

import pytest

from dynqos.common.config import OnboardConfig, build
from dynqos.common.errors import ConfigError
from dynqos.onboard.modem import ModemError, ModemPoller, modem_poller, parse_cell, parse_mmcli, read_mmcli

# The shape of `mmcli -m any --signal-get --output-json` (ModemManager's mmcli-output.c: the keys'
# dotted paths as nested objects, every value a string, "--" where the modem has none).
MMCLI_NR = json.dumps({"modem": {"signal": {
    "refresh": {"rate": "1"},
    "5g": {"rsrp": "-92.00", "rsrq": "-11.00", "snr": "13.50", "error-rate": "--"},
    "lte": {"rsrp": "-97.00", "rsrq": "-12.00", "rssi": "-65.00", "snr": "9.00", "error-rate": "--"},
}}})  # fmt: skip
MMCLI_LTE_ONLY = json.dumps({"modem": {"signal": {
    "5g": {"rsrp": "--", "rsrq": "--", "snr": "--"},
    "lte": {"rsrp": "-101.00", "rsrq": "-13.00", "rssi": "-70.00", "snr": "4.25"},
}}})  # fmt: skip


def test_mmcli_json_gives_nr_values_or_lte_when_there_is_no_nr() -> None:
    assert parse_mmcli(MMCLI_NR) == (-92.0, 13.5)
    assert parse_mmcli(MMCLI_LTE_ONLY) == (-101.0, 4.25)
    assert parse_mmcli(json.dumps({"modem": {"signal": {"refresh": {"rate": "0"}}}})) == (None, None)
    out_of_range = json.dumps({"modem": {"signal": {"5g": {"rsrp": "-400.00", "snr": "99"}}}})
    assert parse_mmcli(out_of_range) == (None, None)  # nothing a modem can report: dropped


@pytest.mark.parametrize(
    "text", ["", "error: couldn't find modem", "[]", '{"modem": {}}', '{"modem": {"signal": 3}}']
)
def test_mmcli_output_that_is_not_a_signal_report_is_an_error(text: str) -> None:
    with pytest.raises(ModemError, match="mmcli"):
        parse_mmcli(text)


def test_a_missing_mmcli_is_a_modem_error_not_a_crash() -> None:
    with pytest.raises(ModemError, match="cannot run"):
        read_mmcli("/nonexistent/mmcli -m any --signal-get --output-json")


def test_the_cells_report_is_read_and_bounded() -> None:
    assert parse_cell({"rsrp_dbm": -77.9, "sinr_db": 15.6, "cqi": 10}) == (-77.9, 15.6)
    assert parse_cell({"rsrp_dbm": -170.0, "sinr_db": -30.0}) == (None, None)
    with pytest.raises(ModemError):
        parse_cell([1, 2])


def test_the_poller_keeps_the_newest_reading_and_survives_failures() -> None:
    answers: list[tuple[float | None, float | None] | ModemError] = [ModemError("no modem"), (-90.0, 10.0)]
    calls = threading.Event()

    def read() -> tuple[float | None, float | None]:
        answer = answers.pop(0) if answers else (-80.0, 20.0)
        if not answers:
            calls.set()
        if isinstance(answer, ModemError):
            raise answer
        return answer

    stop = threading.Event()
    poller = ModemPoller(read, 0.01, time.monotonic_ns, stop, "test")
    poller.start()
    try:
        assert calls.wait(5)
        deadline = time.monotonic() + 5
        while poller.latest is None and time.monotonic() < deadline:
            stop.wait(0.01)
    finally:
        stop.set()
        poller.thread.join(timeout=5)
    assert poller.failures == 1
    assert poller.latest is not None
    assert poller.latest.rsrp_dbm in (-90.0, -80.0)
    assert not poller.thread.is_alive()


def test_modem_settings() -> None:
    assert modem_poller("none", "", "", 1.0, time.monotonic_ns, threading.Event()) is None
    with pytest.raises(ConfigError, match="modem_url"):
        build(OnboardConfig, {"modem": "cell"})
    with pytest.raises(ConfigError, match="modem"):
        build(OnboardConfig, {"modem": "qmi"})
    assert (
        build(OnboardConfig, {"modem": "cell", "modem_url": "http://127.0.0.1:1/radio/uav1"}).modem == "cell"
    )
