"""CANopen reference encoders and resolver readers: the driver (canopen + python-can's socketcand
client) against the gateway fake, over real TCP on loopback, in this process and in another."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import select
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from calibration.robots import nominal
from drivers.canopen_encoder import (
    CanBusConfig,
    CanopenEncoder,
    CanopenEncoderConfig,
    configs_from_endpoint,
    counts_to_angle,
)
from drivers.errors import (
    DeviceConnectionError,
    DeviceFaultError,
    DeviceTimeoutError,
    MeasurementError,
    ProtocolError,
)
from fakes.canopen_nodes import CanGatewayFake, default_mount_offset_rad
from fakes.world import Faults, SimCell

REPO = Path(__file__).resolve().parents[2]
TAU = 2 * math.pi
STEP_RAD = TAU / 2**17  # one count of the simulated multi-turn encoder
HARMONIC = (4e-4, 3.0, 0.5)  # joint 1's gear eccentricity in the truth model: rad, -, rad
TIMEOUT_S = 0.3


def truth_with_eccentricity():
    model = nominal("ur5e")
    joints = list(model.joints)
    joints[0] = dataclasses.replace(joints[0], harmonic=HARMONIC)
    return dataclasses.replace(model, joints=tuple(joints))


@pytest.fixture(scope="module")
def cell():
    return SimCell(truth_with_eccentricity(), seed=3)


@pytest.fixture(scope="module")
def fake(cell):
    gateway = CanGatewayFake(cell, "127.0.0.1", 0, encoders={1: 17, 2: 18}, resolvers={1: 33})
    gateway.start()
    yield gateway
    gateway.stop()


@pytest.fixture(autouse=True)
def clean_cell(request):
    yield
    if "cell" in request.fixturenames:
        cell = request.getfixturevalue("cell")
        cell.faults = Faults()
        move(cell, np.zeros(cell.truth.n_joints))


def move(cell: SimCell, q) -> None:
    """Move the simulated robot (time scale 0: arrives at once)."""
    cell.start_move(np.asarray(q, dtype=float), speed=1.0, accel=1.0)


def config(fake: CanGatewayFake, node_id: int, **kw) -> CanopenEncoderConfig:
    kw.setdefault("timeout_s", TIMEOUT_S)
    kw.setdefault("kind", "resolver" if node_id in fake.resolvers.values() else "encoder")
    return CanopenEncoderConfig(bus=CanBusConfig.from_endpoint(fake.endpoint()["can"]), node_id=node_id, **kw)


def expected_encoder_rad(cell: SimCell, fake: CanGatewayFake, joint: int, node_id: int) -> float:
    return cell.joint_angle(joint) + fake.mount_offset_rad(node_id)


def wait_for_status(enc: CanopenEncoder, *states: str, within_s: float = 3.0) -> str:
    """Poll the driver's NMT/EMCY status until it is one of ``states``."""
    deadline = time.monotonic() + within_s
    while (status := enc.status()) not in states and time.monotonic() < deadline:
        time.sleep(0.02)
    return status


def next_read(cell: SimCell) -> int:
    """The gateway's request count that the next position request will get."""
    return cell.counters.get("canopen.read", 0) + 1


# --------------------------------------------------------------------------- conversions, configs


def test_counts_to_angle_is_turns_plus_angle_within_the_turn():
    cpr, total = 2**17, 2**29
    assert counts_to_angle(cpr // 4, cpr, total) == pytest.approx(math.pi / 2)
    assert counts_to_angle(3 * cpr + cpr // 2, cpr, total) == pytest.approx(3 * TAU + math.pi)
    # the upper half of a multi-turn range reads negative: one count below zero
    assert counts_to_angle(total - 1, cpr, total) == pytest.approx(-TAU / cpr)
    assert counts_to_angle(total - 1, cpr, total, signed=False) == pytest.approx(4095 * TAU + TAU * (cpr - 1) / cpr)
    # single-turn resolver with two pole pairs: electrical half turn = mechanical quarter turn
    assert counts_to_angle(2**15, 2**16, 2**16, pole_pairs=2) == pytest.approx(math.pi / 2)


def test_configs_come_from_the_endpoint_line(fake):
    configs = configs_from_endpoint(fake.endpoint(), use_pdo=True)
    assert sorted(configs) == [("encoder", 1), ("encoder", 2), ("resolver", 1)]
    enc = configs[("encoder", 2)]
    assert (enc.node_id, enc.kind, enc.use_pdo) == (18, "encoder", True)
    assert enc.bus.bus_kwargs() == {
        "interface": "socketcand",
        "channel": "vcan0",
        "host": "127.0.0.1",
        "port": fake.port,
        "tcp_tune": True,
    }
    with pytest.raises(ValueError, match="unknown keys in the `can` endpoint: bogus"):
        CanBusConfig.from_endpoint({**fake.endpoint()["can"], "bogus": 1})
    with pytest.raises(ValueError, match="node_id"):
        CanopenEncoderConfig(bus=enc.bus, node_id=200)


# --------------------------------------------------------------------------- readings


def test_sdo_reading_is_the_true_joint_angle_plus_mount_offset_multi_turn(cell, fake):
    with CanopenEncoder(config(fake, 17)) as enc:
        assert (enc.counts_per_rev, enc.total_range) == (2**17, 2**29)
        sequences = []
        for q1 in (0.0, 1.2, -2.9, 7.5, -8.0):  # beyond one turn both ways
            move(cell, [q1, 0.3, 0, 0, 0, 0])
            reading = enc.read()
            assert reading.angle_rad == pytest.approx(expected_encoder_rad(cell, fake, 1, 17), abs=3 * STEP_RAD)
            assert reading.counts == round(reading.angle_rad / STEP_RAD) % 2**29
            sequences.append(reading.sequence)
        assert sequences == sorted(set(sequences))
        assert enc.status() in ("operational", "no heartbeat")


@pytest.mark.parametrize("trigger", ["sync", "event"])
def test_pdo_readings_are_fresh_after_every_move(cell, fake, trigger):
    with CanopenEncoder(config(fake, 18, use_pdo=True, pdo_trigger=trigger, event_timer_ms=5)) as enc:
        last_sequence = 0
        for q2 in (-1.0, -0.2, 0.9, 2.5):
            move(cell, [0, q2, 0, 0, 0, 0])
            reading = enc.read()
            assert reading.angle_rad == pytest.approx(expected_encoder_rad(cell, fake, 2, 18), abs=3 * STEP_RAD)
            assert reading.sequence > last_sequence
            last_sequence = reading.sequence


@pytest.mark.parametrize("use_pdo", [False, True])
def test_resolver_reads_the_16_bit_angle(cell, fake, use_pdo):
    with CanopenEncoder(config(fake, 33, use_pdo=use_pdo)) as res:
        assert (res.counts_per_rev, res.total_range, res.pole_pairs) == (65536, 65536, 1)
        for q1 in (0.4, -1.7):
            move(cell, [q1, 0, 0, 0, 0, 0])
            reading = res.read()
            expected = (cell.joint_angle(1) + fake.mount_offset_rad(33)) % TAU
            assert 0 <= reading.angle_rad < TAU
            assert reading.angle_rad == pytest.approx(expected, abs=5 * TAU / 65536)


def test_resolver_with_pole_pairs_gives_the_mechanical_angle_modulo_one_pole_pitch():
    cell = SimCell(nominal("ur5e"), seed=1)
    with CanGatewayFake(cell, "127.0.0.1", 0, encoders={}, resolvers={4: 40}, resolver_pole_pairs=3) as fake:
        move(cell, [0, 0, 0, 1.1, 0, 0])
        with CanopenEncoder(config(fake, 40)) as res:
            assert res.pole_pairs == 3
            reading = res.read()
        pitch = TAU / 3
        expected = (1.1 + fake.mount_offset_rad(40)) % pitch
        assert reading.angle_rad == pytest.approx(expected, abs=5 * TAU / 65536 / 3)


def test_gear_eccentricity_is_visible_in_a_joint_sweep():
    """Sweep joint 1; the reference encoder minus the controller's reading is offset plus the
    eq. 2.4 harmonic A sin(k q + phi) of the truth model (k known from the design). Its own cell
    and gateway: a fit to a few counts must not depend on what earlier tests left in the
    module's (a sensor fault injected on another node made it 5 % off)."""
    amplitude, k, phase = HARMONIC
    q = np.linspace(-math.pi, math.pi, 37)
    measured = []
    cell = SimCell(truth_with_eccentricity(), seed=3)
    with (
        CanGatewayFake(cell, "127.0.0.1", 0, encoders={1: 17}, resolvers={}) as fake,
        CanopenEncoder(config(fake, 17, use_pdo=True)) as enc,
    ):
        for q1 in q:
            move(cell, [q1, 0, 0, 0, 0, 0])
            measured.append(enc.read().angle_rad)
    residual = np.unwrap(np.array(measured)) - q
    design = np.column_stack([np.ones_like(q), np.sin(k * q), np.cos(k * q)])
    (offset, s, c), *_ = np.linalg.lstsq(design, residual, rcond=None)
    assert math.hypot(s, c) == pytest.approx(amplitude, abs=2e-5)
    assert math.atan2(c, s) == pytest.approx(phase, abs=0.05)
    assert (offset - fake.mount_offset_rad(17) + math.pi) % TAU - math.pi == pytest.approx(0, abs=2e-5)


# --------------------------------------------------------------------------- across processes


def start_fake_process(*args: str) -> tuple[subprocess.Popen, dict]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "fakes.canopen_nodes", "--host", "127.0.0.1", "--port", "0", *args],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    ready, _, _ = select.select([proc.stdout], [], [], 30)
    line = proc.stdout.readline() if ready else ""
    if not line:
        proc.kill()
        raise AssertionError(f"the fake printed no ready line: {proc.communicate()[1]}")
    return proc, json.loads(line)


def test_other_process_gateway_serves_sdo_and_pdo_reads():
    q = [0.25, -1.1, 0.7, 0.0, 0.0, 0.0]
    proc, endpoint = start_fake_process("--q", ",".join(map(str, q)), "--resolvers", "1:33,3:34", "--silent-node", "34")
    try:
        assert endpoint["ready"] is True
        assert endpoint["can"]["interface"] == "socketcand" and endpoint["can"]["channel"] == "vcan0"
        assert endpoint["encoders"] == {"1": 17, "2": 18}
        configs = configs_from_endpoint(endpoint, timeout_s=TIMEOUT_S)
        with (
            CanopenEncoder(configs[("encoder", 1)]) as e1,
            CanopenEncoder(dataclasses.replace(configs[("encoder", 2)], use_pdo=True)) as e2,
            CanopenEncoder(configs[("resolver", 1)]) as r1,
        ):
            for enc, joint, node_id, tol in ((e1, 1, 17, 3 * STEP_RAD), (e2, 2, 18, 3 * STEP_RAD)):
                first, second = enc.read(), enc.read()
                assert second.sequence == first.sequence + 1
                expected = q[joint - 1] + default_mount_offset_rad(node_id)
                assert first.angle_rad == pytest.approx(expected, abs=tol)
            expected = (q[0] + default_mount_offset_rad(33)) % TAU
            assert r1.read().angle_rad == pytest.approx(expected, abs=5 * TAU / 65536)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeoutError, match=r"node 34.*no SDO answer"):
            CanopenEncoder(configs[("resolver", 3)])
        assert time.monotonic() - t0 < 2.0
    finally:
        proc.terminate()
        _, stderr = proc.communicate(timeout=10)
    assert proc.returncode == 0, stderr


# --------------------------------------------------------------------------- device faults


@pytest.mark.parametrize(
    "fault, node_id, use_pdo, error, match, status",
    [
        (
            "sensor_fault_at=2",
            17,
            False,
            DeviceFaultError,
            r"SDO abort .*hardware error.*EMCY 0x7320 \(position sensor\) \(code 0x06060000\)",
            "fault: EMCY 0x7320 (position sensor)",
        ),
        (
            "sensor_fault_at=2",
            33,
            True,
            MeasurementError,
            r"resolver reports LOS loss of signal, LOT loss of tracking \(code 0x05\)",
            "fault: EMCY 0x7300 (sensor)",
        ),
        ("garble_at=2", 17, False, ProtocolError, "unexpected SDO answer 0xBC", "operational"),
        ("garble_at=2", 18, True, ProtocolError, "TPDO1 of 2 bytes does not hold 0x6004", "operational"),
    ],
    ids=["encoder-sensor-fault-sdo", "resolver-fault-pdo", "garbled-sdo", "garbled-pdo"],
)
def test_faults_of_a_node_in_another_process(fault_cell, fault, node_id, use_pdo, error, match, status):
    """``recal fake-cell`` with the fault (counted per position request: SDO upload of 0x6004
    or SYNC): the first reading is good, the second fails with the driver's error naming the
    node, ``status()`` tells the node's EMCY, and the next reading is good again.
    (Frames later than the timeout: tests/drivers/test_late_replies.py.)"""
    cell = fault_cell(only=("can",), faults=(fault,))
    kind = "resolver" if node_id == 33 else "encoder"
    bus = CanBusConfig.from_endpoint(cell.endpoint["can"])
    with CanopenEncoder(
        CanopenEncoderConfig(bus=bus, node_id=node_id, kind=kind, use_pdo=use_pdo, timeout_s=TIMEOUT_S)
    ) as enc:
        first = enc.read()
        with pytest.raises(error, match=match) as info:
            enc.read()
        assert f"node {node_id} on socketcand vcan0@{cell.host}" in str(info.value)
        assert wait_for_status(enc, status) == status
        third = enc.read()
        assert wait_for_status(enc, "operational") == "operational"
    assert third.sequence == 2
    tolerance = 5 * TAU / 65536 if kind == "resolver" else 3 * STEP_RAD
    assert third.angle_rad == pytest.approx(first.angle_rad, abs=tolerance)  # the robot stands still


def test_silent_node_in_another_process_is_a_timeout_and_the_others_answer(fault_cell):
    cell = fault_cell(only=("can",), faults=("silent_nodes=18",))
    configs = configs_from_endpoint(cell.endpoint, timeout_s=TIMEOUT_S)
    t0 = time.monotonic()
    expected = "node 18 .*no SDO answer reading the device configuration within 0.3 s"
    with pytest.raises(DeviceTimeoutError, match=expected):
        CanopenEncoder(configs[("encoder", 2)])
    assert time.monotonic() - t0 < 2 * TIMEOUT_S + 0.5
    with CanopenEncoder(configs[("encoder", 1)]) as enc:
        assert enc.read().angle_rad == pytest.approx(default_mount_offset_rad(17), abs=3 * STEP_RAD)


def test_encoder_sensor_fault_in_pdo_mode_names_the_emcy(cell, fake):
    with CanopenEncoder(config(fake, 18, use_pdo=True)) as enc:
        enc.read()
        cell.faults.sensor_fault_at = [next_read(cell)]
        with pytest.raises(DeviceFaultError, match=r"no TPDO1 .*EMCY 0x7320") as info:
            enc.read()
        assert info.value.code == "0x7320"
        assert enc.read().sequence == 2


def test_resolver_fault_bits_refuse_an_sdo_reading(cell, fake):
    with CanopenEncoder(config(fake, 33)) as res:
        cell.faults.sensor_fault_at = [next_read(cell)]
        with pytest.raises(MeasurementError, match="LOS loss of signal, LOT loss of tracking") as info:
            res.read()
        assert info.value.code == "0x05"
        assert res.read().sequence == 1  # the failed reading got no sequence number


def test_sdo_abort_for_an_object_the_node_lacks_is_a_protocol_error(fake):
    """Configured as a resolver reader but node 17 is an encoder: no pole-pairs object 0x2001."""
    with pytest.raises(ProtocolError, match=r"node 17.*SDO abort.*Object does not exist") as info:
        CanopenEncoder(config(fake, 17, kind="resolver"))
    assert info.value.code == "0x06020000"


# --------------------------------------------------------------------------- link faults


@pytest.mark.parametrize("use_pdo", [False, True])
def test_silent_node_times_out_and_is_read_again_when_back(cell, fake, use_pdo):
    with CanopenEncoder(config(fake, 18, use_pdo=use_pdo)) as enc:
        enc.read()
        cell.faults.silent_nodes = [18]
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeoutError, match=r"node 18.*within 0.3 s"):
            enc.read()
        assert time.monotonic() - t0 < TIMEOUT_S + 0.3
        cell.faults.silent_nodes = []
        move(cell, [0, 0.6, 0, 0, 0, 0])
        reading = enc.read()
        assert reading.angle_rad == pytest.approx(expected_encoder_rad(cell, fake, 2, 18), abs=3 * STEP_RAD)
        assert reading.sequence == 2


@pytest.mark.parametrize("use_pdo", [False, True])
def test_dropped_connection_reconnects_and_reads_fresh(cell, fake, use_pdo):
    with CanopenEncoder(config(fake, 17, use_pdo=use_pdo)) as enc:
        enc.read()
        cell.faults.drop_connection_at = [next_read(cell)]
        move(cell, [-0.8, 0, 0, 0, 0, 0])
        reading = enc.read()
        assert enc.reconnects == 1
        assert reading.sequence == 2
        assert reading.angle_rad == pytest.approx(expected_encoder_rad(cell, fake, 1, 17), abs=3 * STEP_RAD)


def test_rebooted_node_is_set_up_again(cell, fake):
    with CanopenEncoder(config(fake, 18, use_pdo=True)) as enc:
        enc.read()
        fake.reboot_node(18)  # back in PRE-OPERATIONAL with the default PDO configuration
        assert wait_for_status(enc, "boot-up", "pre-operational") in ("boot-up", "pre-operational")
        move(cell, [0, 1.4, 0, 0, 0, 0])
        reading = enc.read()
        assert reading.angle_rad == pytest.approx(expected_encoder_rad(cell, fake, 2, 18), abs=3 * STEP_RAD)
        assert wait_for_status(enc, "operational") == "operational"


def test_gateway_gone_is_a_connection_error_quickly(cell):
    gateway = CanGatewayFake(cell, "127.0.0.1", 0, encoders={1: 17}, resolvers={})
    gateway.start()
    enc = CanopenEncoder(config(gateway, 17))
    try:
        enc.read()
        gateway.stop()
        t0 = time.monotonic()
        with pytest.raises(DeviceConnectionError, match=r"node 17.*(connect|link lost)"):
            enc.read()
        assert time.monotonic() - t0 < 2.0
        assert enc.status() == "disconnected"
    finally:
        enc.close()
    t0 = time.monotonic()
    with pytest.raises(DeviceConnectionError, match=r"cannot connect to socketcand server 127.0.0.1"):
        CanopenEncoder(config(gateway, 17))
    assert time.monotonic() - t0 < 1.0


def test_wrong_channel_is_a_connection_error(fake):
    bus = dataclasses.replace(CanBusConfig.from_endpoint(fake.endpoint()["can"]), channel="can7")
    with pytest.raises(DeviceConnectionError, match="cannot open channel 'can7': < error could not open bus"):
        CanopenEncoder(CanopenEncoderConfig(bus=bus, node_id=17, timeout_s=TIMEOUT_S))


def test_something_else_on_the_port_is_a_protocol_error():
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def greet_wrongly():
        conn, _ = server.accept()
        with conn:
            conn.sendall(b"220 smtp ready\r\n")

    threading.Thread(target=greet_wrongly, daemon=True).start()
    bus = CanBusConfig(interface="socketcand", channel="vcan0", host="127.0.0.1", port=port)
    try:
        with pytest.raises(ProtocolError, match="greeted with b'220 smtp ready"):
            CanopenEncoder(CanopenEncoderConfig(bus=bus, node_id=17))
    finally:
        server.close()


def test_status_follows_heartbeat_and_emcy(cell, fake):
    enc = CanopenEncoder(config(fake, 17))
    assert wait_for_status(enc, "operational") == "operational"
    cell.faults.sensor_fault_at = [next_read(cell)]
    with pytest.raises(DeviceFaultError):
        enc.read()
    assert enc.status().startswith("fault: EMCY 0x7320 (position sensor)")
    enc.read()
    assert enc.status() == "operational"
    enc.close()
    enc.close()  # idempotent
    assert enc.status() == "disconnected"
    with pytest.raises(DeviceConnectionError, match="closed"):
        enc.read()
