"""The lab's package, installed beside feedbench and configured only through its own
tables: `feedbench run` on the simulated bench, `analyze`, `report`, the live analysis equal
to the offline one, `feedbench sim` serving its simulated peer, the demo and a campaign
running its example, and the host's checks of its device table."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import threading
import tomllib
from pathlib import Path

import pytest

import feedbench
from feedbench.bench import parse_run_config, run_axis
from feedbench.commands.campaign import parse_campaign, run_task
from feedbench.commands.cli import main
from feedbench.config import OWN_DISTRIBUTION, ConfigError
from feedbench.commands.demo import campaign_config, measure
from feedbench.drivers.modbus_devices import ModbusDevice, connect_tcp
from feedbench.devices import devices
from feedbench.engine.family import LAB_RANK, examples, families
from feedbench.sim_backends.process import READY, simulated_peers
from feedbench.testing import assert_live_equals_offline, virtual_channel

from lab_extension.linear_scale import LinearScaleDevice
from lab_extension.linear_scale_peer import LinearScalePeer
from lab_extension.protocol import SCALE_MAP, STATUS_SIGNAL_OK
from lab_extension.settling_time import SettlingTime

EXAMPLE = examples()["settling_time"]


def _quick(directory: Path) -> dict:
    """The example, --quick (two moves), on its own virtual channel, writing to `directory`."""
    raw = campaign_config(EXAMPLE, directory, quick=True)
    raw["bench"]["channel"] = virtual_channel("lab")
    return raw


def _truth(raw: dict) -> dict:
    return run_axis(raw).truth(raw["bench"]["world"])


def test_the_package_registers_its_family_kind_and_peer_and_feedbench_names_none():
    assert families()["settling_time"] is SettlingTime
    assert devices()["linear_scale"] is LinearScaleDevice
    assert simulated_peers()["linear_scale"] is LinearScalePeer
    assert "settling_time" not in families(OWN_DISTRIBUTION)
    assert EXAMPLE.package == "lab_extension" and EXAMPLE.rank == LAB_RANK
    assert list(examples())[-1] == "settling_time"  # after feedbench's own
    source = Path(feedbench.__file__).parent
    for path in source.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert "settling_time" not in text and "linear_scale" not in text, path


def test_run_analyze_report_on_the_simulated_bench(tmp_path, capsys):
    """`feedbench run`, `analyze`, `report`: the residual vibration at the tool tip within
    2 % of the world's anti-resonance f_t (Eq. 4.13), both moves settled within the band;
    the live result equals `analyze`'s."""
    raw = _quick(tmp_path)
    config = tmp_path / "settling.toml"
    config.write_text(_toml(raw))
    assert main(["run", str(config), "--json"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert row["status"] == "complete", row["reason"]
    assert main(["analyze", row["file"], "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["valid"], result["not_valid_because"]
    assert len(result["moves"]) == 2
    f_t = _truth(raw)["f_t_hz"]
    assert result["frequency_hz"] == pytest.approx(f_t, rel=0.02)
    assert 0.2 < result["settling_s_max"] < raw["experiment"]["dwell_s"] * 0.8
    for move in result["moves"]:
        assert move["travel_m"] == pytest.approx(move["stroke_m"], rel=1e-3)
        assert move["settled"] and move["overshoot_m"] > 5e-6
    assert assert_live_equals_offline(row["file"]).version >= 1
    report = tmp_path / "report.html"
    assert main(["report", row["file"], "-o", str(report)]) == 0
    html = report.read_text()
    assert "settling after each move (linear scale)" in html and "settling per move" in html


def test_the_demo_and_a_campaign_run_its_example(tmp_path):
    """The demo's `measure` of the example (what `feedbench demo` runs for each declared
    example): its summary against the lab axis's truth, its report section; a campaign
    over the settling band from the example, one task run as a worker runs it."""
    raw = _quick(tmp_path / "demo")
    measured = measure(EXAMPLE, raw)
    assert measured.entry["run"]["status"] == "complete"
    assert abs(measured.entry["summary"]["error_pct"]) < 2.0
    assert "vs f_t (Eq. 4.13)" in measured.entry["headline"]
    assert measured.section is not None
    base = _quick(tmp_path / "campaign")
    campaign = parse_campaign({**base, "campaign": {"kind": "grid", "seeds": [0, 1],
                                                    "grid": {"experiment.band_um": [2.0, 5.0]}}})
    assert len(campaign.tasks) == 4 and campaign.experiment == "settling_time"
    row = run_task(campaign.tasks[-1], campaign.id)
    assert row["status"] == "complete", row["reason"]
    assert row["params"]["experiment.band_um"] == 5.0
    assert row["results"]["settling_s_max"] < measured.entry["summary"]["settling_s_max"]


def test_its_tables_are_checked_by_its_kind_and_peer(tmp_path, simulated_bench):
    """An unknown key in ``[bench.devices.linear_scale]`` (the kind's schema) or in
    ``[bench.world.linear_scale]`` (the peer's) is one line naming it."""
    raw = _quick(tmp_path)
    raw["bench"]["devices"]["linear_scale"]["every_n"] = 2
    with pytest.raises(ConfigError, match=r"^bench.devices.linear_scale.every_n: unknown key"):
        parse_run_config(raw)
    raw = _quick(tmp_path)
    raw["bench"]["world"]["linear_scale"]["resolution_um"] = 0.1
    with pytest.raises(ConfigError, match=r"^bench.world.linear_scale.resolution_um: unknown "
                                          r"key \(known: noise_nm, resolution_nm, seed\)$"):
        with simulated_bench.open(raw):  # the peer's table, checked as the bench starts
            pass


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_feedbench_sim_serves_its_peer(tmp_path):
    """`feedbench sim` on the lab axis serves every registered peer, this package's too, at
    its table's address and unit id: the ready line and the host table name it, and the
    host's driver reads the simulated scale's registers over Modbus TCP."""
    port = _free_port()
    config = tmp_path / "sim.toml"
    config.write_text("\n".join([
        "[bench]", "simulated = true", 'interface = "socketcand"',
        'socketcand = "127.0.0.1:0"', f'channel = "{virtual_channel("lab-sim")}"',
        "[bench.devices.linear_scale]", f'address = "127.0.0.1:{port}"', "unit_id = 12",
        "[bench.world.linear_scale]", "resolution_nm = 100.0"]) + "\n")
    process = subprocess.Popen([sys.executable, "-m", "feedbench.commands.cli", "sim", str(config)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stderr: list[str] = []
    reader = threading.Thread(target=lambda: stderr.extend(process.stderr), daemon=True)
    reader.start()
    try:
        line = process.stdout.readline()
        assert line.startswith(READY), "".join(stderr)
        info = json.loads(line[len(READY):])
        assert info["devices"]["linear_scale"] == {"address": f"127.0.0.1:{port}",
                                                   "unit_id": 12}
        assert info["modbus_devices"]["linear scale reader"] == 12
        host_table = process.stdout.readline()
        while not host_table.startswith("devices.linear_scale"):
            host_table = process.stdout.readline()
        client = connect_tcp("127.0.0.1", port)
        try:
            values = ModbusDevice(client, 12, SCALE_MAP).read_all()
        finally:
            client.close()
        assert values["STATUS"] == STATUS_SIGNAL_OK and math.isfinite(values["POSITION"])
    finally:
        process.terminate()
        code = process.wait(timeout=20)
        reader.join(5)
    assert code == 0, "".join(stderr)


def _toml(raw: dict) -> str:
    """A run config as TOML (tables and dotted sub-tables; values as JSON writes them,
    which TOML reads for the numbers, strings, booleans and lists used here)."""
    lines = []

    def table(name: str, values: dict) -> None:
        scalars = {k: v for k, v in values.items() if not isinstance(v, dict)}
        lines.append(f"[{name}]")
        lines.extend(f"{key} = {json.dumps(value)}" for key, value in scalars.items())
        for key, value in values.items():
            if isinstance(value, dict):
                table(f"{name}.{key}", value)

    for name, values in raw.items():
        table(name, values)
    text = "\n".join(lines) + "\n"
    assert tomllib.loads(text) == raw
    return text
