"""The emScon tracker: the fake proven with ``cesapi`` (an independent emScon client), the bytes
our driver writes decoded with ``cesapi``'s packet classes, the driver against the fake, the
fake's beam geometry, and each injectable fault across processes."""

from __future__ import annotations

import dataclasses
import select
import socket
import struct
import threading
import time

import numpy as np
import pytest

CESAPI = pytest.importorskip("CESAPI.packet", reason="cesapi (the test extra) is the independent emScon client")
from CESAPI import packet as P  # noqa: E402
from CESAPI.command import CommandSync  # noqa: E402
from CESAPI.connection import Connection  # noqa: E402

from calibration.kinematics import fk  # noqa: E402
from calibration.robots import nominal  # noqa: E402
from drivers.errors import (  # noqa: E402
    DeviceConnectionError,
    DeviceFaultError,
    DeviceTimeoutError,
    MeasurementError,
    ProtocolError,
)
from drivers.leica_emscon import COMMAND_PARAMS, EmsconConfig, EmsconTracker  # noqa: E402
from fakes.leica_tracker import LeicaTrackerFake  # noqa: E402
from fakes.world import SimCell  # noqa: E402

REFLECTOR_TOOL = np.array([0.0, 0.0, 0.05])
Q_POSE = np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.2])


@pytest.fixture(scope="module")
def truth():
    return dataclasses.replace(nominal("ur5e"), targets={"smr1": REFLECTOR_TOOL})


@pytest.fixture
def cell(truth):
    return SimCell(truth, seed=3, q_home=Q_POSE)


@pytest.fixture
def fake(cell):
    f = LeicaTrackerFake(cell, port=0)
    f.start()
    yield f
    f.stop()


def _config(fake, **kw) -> EmsconConfig:
    return EmsconConfig(host="127.0.0.1", port=fake.port, **{"timeout_s": 1.0, "measure_time_s": 0.1, **kw})


def _sigma_m(cell) -> float:
    r = float(np.linalg.norm(cell.target_world()))
    return 0.5 * (cell.noise.tracker_mpe_const_m + cell.noise.tracker_mpe_per_m * r) / np.sqrt(3.0)


# --------------------------------------------------------------------------- a recording proxy


class Proxy:
    """A TCP relay between a client and the fake that keeps every byte each way."""

    def __init__(self, port: int):
        self.upstream = port
        self.to_server = bytearray()
        self.to_client = bytearray()
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self._threads: list[threading.Thread] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            try:
                client, _ = self.server.accept()
            except OSError:
                return
            upstream = socket.create_connection(("127.0.0.1", self.upstream))
            for src, dst, log in ((client, upstream, self.to_server), (upstream, client, self.to_client)):
                t = threading.Thread(target=self._pump, args=(src, dst, log), daemon=True)
                t.start()
                self._threads.append(t)

    @staticmethod
    def _pump(src, dst, log):
        while True:
            try:
                data = src.recv(65536)
            except OSError:
                data = b""
            if not data:
                for s in (src, dst):
                    try:
                        s.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass
                return
            log += data
            dst.sendall(data)

    def close(self):
        self.server.close()


def _split(data: bytes) -> list[bytes]:
    out = []
    while data:
        size = struct.unpack_from("<i", data)[0]
        out.append(data[:size])
        data = data[size:]
    return out


# --------------------------------------------------------------------------- cesapi drives the fake


def test_cesapi_drives_the_fake_through_every_command_the_driver_sends(fake, cell):
    """The independent client sends each command our driver uses, built and parsed by its own
    packet classes, and gets the answers a real emScon server gives."""
    connection = Connection()
    connection.connect(host="127.0.0.1", port=fake.port)
    try:
        cmd = CommandSync(connection)
        status = cmd.GetSystemStatus()
        assert status.packetInfo.status == P.ES_RS_AllOK
        assert status.trackerProcessorStatus != P.ES_TPS_Initialized  # a tracker just powered up
        assert status.weatherMonitorStatus == P.ES_WMS_ReadAndCalculateRefractions
        assert (status.esVersionNumber.iMajorVersionNumber, status.esVersionNumber.iMinorVersionNumber) == (3, 8)
        assert cmd.GetTrackerStatus().trackerStatus == P.ES_TS_NotReady
        cmd.Initialize()
        assert cmd.GetSystemStatus().trackerProcessorStatus == P.ES_TPS_Initialized
        assert cmd.GetTrackerStatus().trackerStatus == P.ES_TS_Ready

        units = P.SystemUnitsDataT()
        units.lenUnitType, units.angUnitType = P.ES_LU_Meter, P.ES_AU_Degree
        units.tempUnitType, units.pressUnitType, units.humUnitType = P.ES_TU_Celsius, P.ES_PU_Mbar, P.ES_HU_RH
        cmd.SetUnits(units)
        assert cmd.GetCoordinateSystemType().coordSysType == P.ES_CS_RHR
        env = P.EnvironmentDataT()
        env.dTemperature, env.dPressure, env.dHumidity = 21.5, 990.0, 40.0
        cmd.SetEnvironmentParams(env)
        got = cmd.GetEnvironmentParams().environmentData
        assert (got.dTemperature, got.dPressure, got.dHumidity) == (21.5, 990.0, 40.0)

        first = cmd.GetReflectors()  # the server sends one reply per reflector; cesapi keeps the first
        assert first.iTotalReflectors == 3
        assert first.cReflectorName.decode("utf-16-le").rstrip("\x00") == "RRR 1.5in"
        assert first.targetType == P.ES_TT_RRR15 and first.dSurfaceOffset == pytest.approx(19.05)
        cmd.SetReflector(first.iInternalReflectorId)
        cmd.SetMeasurementMode(P.ES_MM_Stationary)
        stationary = P.StationaryModeDataT()
        stationary.lMeasTime, stationary.bUseADM = 100, 0
        cmd.SetStationaryModeParams(stationary)

        info = cmd.GetMeasurementStatusInfo()
        assert info.lMeasurementStatusInfo & P.ES_MSI_ReflectorFound
        result = cmd.StartMeasurement()
        assert P.packetType(result) == P.ES_DT_SingleMeasResult
        p = np.array([result.dVal1, result.dVal2, result.dVal3])  # metres: the units set above
        sigma = _sigma_m(cell)
        assert result.dStd1 == pytest.approx(sigma)
        assert np.all(np.abs(p - cell.target_world()) < 5 * sigma)
        assert (result.dTemperature, result.dPressure) == (21.5, 990.0)

        target = cell.target_world()
        cmd.GoPosition(0, *(target + [0.03, -0.02, 0.01]))
        assert not cmd.GetMeasurementStatusInfo().lMeasurementStatusInfo & P.ES_MSI_ReflectorFound
        cmd.FindReflector(float(np.linalg.norm(target)))
        assert cmd.GetMeasurementStatusInfo().lMeasurementStatusInfo & P.ES_MSI_ReflectorFound

        with pytest.raises(Exception, match="failed with status 2"):  # ES_RS_NotImplemented
            cmd.Park()  # outside the fake's subset (ParkRT is a bare reply)
    finally:
        connection.disconnect()


def test_the_bytes_the_driver_writes_decode_with_cesapi(fake, cell):
    """Every packet our driver sends, parsed by cesapi's classes, has the intended fields, is of
    the size cesapi's class has, and packs back to the same bytes; every answer the fake sends
    parses with cesapi too, and the measurements the driver returns are the results as cesapi
    reads them. Two connections: the environment from the config, then from the weather station
    (``GetEnvironmentParams``) with the distance meter alone (``bUseADM``)."""
    proxy = Proxy(fake.port)
    try:
        with EmsconTracker(
            EmsconConfig(
                host="127.0.0.1",
                port=proxy.port,
                timeout_s=1.0,
                measure_time_s=0.25,
                environment="config",
                temperature_c=19.5,
                pressure_mbar=1001.0,
                humidity_pct=35.0,
                reflector="RRR 0.5in",
            )
        ) as tracker:
            measured = [tracker.measure()]
            target = cell.target_world()
            tracker.find_reflector(target)
            assert tracker.status() == "ready"
        with EmsconTracker(EmsconConfig(host="127.0.0.1", port=proxy.port, timeout_s=1.0, use_adm=True)) as tracker:
            assert tracker.environment == (19.5, 1001.0, 35.0)  # what the first connection set, read back
            measured.append(tracker.measure())
    finally:
        proxy.close()
    factory = P.PacketFactory()
    raws = _split(bytes(proxy.to_server))
    sent = [factory.packet(raw, return_type=False) for raw in raws]
    for raw, packet in zip(raws, sent):
        assert packet.pack() == raw
        assert type(packet)().packetInfo.packetHeader.lPacketSize == len(raw)  # cesapi's own size of it
    commands = [p.packetInfo.command for p in sent]
    set_up = [
        P.ES_C_SetUnits,
        P.ES_C_GetCoordinateSystemType,
    ]
    selection = [P.ES_C_GetReflectors, P.ES_C_SetReflector, P.ES_C_SetMeasurementMode, P.ES_C_SetStationaryModeParams]
    first = [
        P.ES_C_GetSystemStatus,
        P.ES_C_GetTrackerStatus,
        P.ES_C_Initialize,
        *set_up,
        P.ES_C_SetEnvironmentParams,
        *selection,
        P.ES_C_StartMeasurement,
        P.ES_C_GoPosition,
        P.ES_C_FindReflector,
        P.ES_C_GetMeasurementStatusInfo,
    ]
    second = [
        P.ES_C_GetSystemStatus,
        P.ES_C_GetTrackerStatus,  # initialised by the first connection: no Initialize
        *set_up,
        P.ES_C_GetEnvironmentParams,
        *selection,
        P.ES_C_StartMeasurement,
    ]
    assert commands == first + second
    # every command the driver can send (drivers/leica_emscon.py) went through cesapi's classes
    assert set(commands) == set(COMMAND_PARAMS)
    by = dict(zip(commands, sent))
    u = by[P.ES_C_SetUnits].unitsSettings
    assert (u.lenUnitType, u.angUnitType, u.tempUnitType, u.pressUnitType, u.humUnitType) == (
        P.ES_LU_Millimeter,
        P.ES_AU_Degree,
        P.ES_TU_Celsius,
        P.ES_PU_Mbar,
        P.ES_HU_RH,
    )
    e = by[P.ES_C_SetEnvironmentParams].environmentData
    assert (e.dTemperature, e.dPressure, e.dHumidity) == (19.5, 1001.0, 35.0)
    set_reflector = [p for p in sent if p.packetInfo.command == P.ES_C_SetReflector]
    assert [p.iInternalReflectorId for p in set_reflector] == [1, 0]  # RRR 0.5in, then the default RRR 1.5in
    assert all(p.measMode == P.ES_MM_Stationary for p in sent if p.packetInfo.command == P.ES_C_SetMeasurementMode)
    stationary = [p.stationaryModeData for p in sent if p.packetInfo.command == P.ES_C_SetStationaryModeParams]
    assert [(d.lMeasTime, d.bUseADM) for d in stationary] == [(250, 0), (500, 1)]
    go = by[P.ES_C_GoPosition]
    assert np.allclose([go.dVal1, go.dVal2, go.dVal3], target * 1e3) and go.bUseADM == 0
    assert by[P.ES_C_FindReflector].dAproxDistance == pytest.approx(np.linalg.norm(target) * 1e3)

    raws = _split(bytes(proxy.to_client))
    answers = [factory.packet(raw) for raw in raws]
    assert all(a is not None for a in answers)
    for raw, a in zip(raws, answers):  # replies, results and status changes: each of cesapi's size
        fresh = type(a)()
        header = fresh.packetInfo.packetHeader if hasattr(fresh, "packetInfo") else fresh.packetHeader
        assert header.lPacketSize == len(raw), type(a).__name__
    assert {P.packetType(a) for a in answers} == {P.ES_DT_Command, P.ES_DT_SingleMeasResult, P.ES_DT_SystemStatusChange}
    replies = [a.packetInfo.command for a in answers if P.packetType(a) == P.ES_DT_Command]
    assert replies.count(P.ES_C_GetReflectors) == 6 and len(replies) == len(commands) + 4
    results = [a for a in answers if P.packetType(a) == P.ES_DT_SingleMeasResult]
    assert len(results) == 2
    for r, m in zip(results, measured):  # millimetres on the wire, metres from the driver
        assert np.array_equal(m.p_world, np.array([r.dVal1, r.dVal2, r.dVal3]) * 1e-3)
        assert np.array_equal(m.sigma, np.array([r.dStd1, r.dStd2, r.dStd3]) * 1e-3)


def test_cesapi_reads_the_extended_result_as_the_driver_does(cell):
    """The fake's ``SingleMeasResult2T`` (with covariances), read by cesapi: the position, the
    deviations and the weather in their places; the driver returns the same values."""
    fake = LeicaTrackerFake(cell, port=0, extended_result=True, initialised=True)
    fake.start()
    proxy = Proxy(fake.port)
    try:
        connection = Connection()
        connection.connect(host="127.0.0.1", port=fake.port)
        try:
            result = CommandSync(connection).StartMeasurement()  # the fake starts in millimetres
        finally:
            connection.disconnect()
        assert P.packetType(result) == P.ES_DT_SingleMeasResult2
        sigma_mm = _sigma_m(cell) * 1e3
        assert (result.dStd1, result.dStd2, result.dStd3) == pytest.approx((sigma_mm,) * 3)
        assert (result.dAprioriStd1, result.dAprioriStdTotal) == pytest.approx((sigma_mm, np.sqrt(3) * sigma_mm))
        assert (result.dTemperature, result.dPressure, result.dHumidity) == fake.environment
        p_mm = np.array([result.dVal1, result.dVal2, result.dVal3])
        assert np.all(np.abs(p_mm - cell.target_world() * 1e3) < 5 * sigma_mm)

        with EmsconTracker(_config(proxy)) as tracker:
            m = tracker.measure()
    finally:
        proxy.close()
        fake.stop()
    ((raw, r),) = [
        (raw, a)
        for raw in _split(bytes(proxy.to_client))
        if P.packetType(a := P.PacketFactory().packet(raw)) == P.ES_DT_SingleMeasResult2
    ]
    assert len(raw) == P.SingleMeasResult2T().packetInfo.packetHeader.lPacketSize  # cesapi's size: 204
    assert np.array_equal(m.p_world, np.array([r.dVal1, r.dVal2, r.dVal3]) * 1e-3)
    assert np.array_equal(m.sigma, np.array([r.dStd1, r.dStd2, r.dStd3]) * 1e-3)


# --------------------------------------------------------------------------- the driver against the fake


def test_measure_is_the_true_reflector_within_its_reported_sigma(fake, cell):
    sigma = _sigma_m(cell)
    with EmsconTracker(_config(fake)) as tracker:
        assert tracker.identity.server_version == "3.8.400"
        assert tracker.reflector.name == "RRR 1.5in"
        assert tracker.environment == (20.0, 1013.25, 50.0)  # read from the weather station
        assert tracker.status() == "ready"
        points = []
        for i in range(15):
            m = tracker.measure()
            assert m.sequence == i + 1
            assert np.allclose(m.sigma, sigma)
            assert np.all(np.abs(m.p_world - cell.target_world()) < 5 * sigma)
            points.append(m.p_world)
    assert np.std(np.array(points) - cell.target_world()) > 0.3 * sigma  # the noise is there
    assert fake.initialised  # the driver initialised the tracker it found uninitialised


def test_extended_result_is_taken(cell):
    fake = LeicaTrackerFake(cell, port=0, extended_result=True, initialised=True)
    fake.start()
    try:
        with EmsconTracker(_config(fake)) as tracker:
            m = tracker.measure()
        assert np.allclose(m.sigma, _sigma_m(cell))
        assert np.all(np.abs(m.p_world - cell.target_world()) < 5 * _sigma_m(cell))
    finally:
        fake.stop()


def test_measurement_follows_the_robot(fake, cell, truth):
    with EmsconTracker(_config(fake)) as tracker:
        first = tracker.measure()
        cell.start_move(Q_POSE + 0.2, 1.0, 1.0)
        second = tracker.measure()
    expected = fk(truth, (Q_POSE + 0.2)[None])[0]
    assert np.linalg.norm(second.p_world - (expected[:3, :3] @ REFLECTOR_TOOL + expected[:3, 3])) < 1e-4
    assert np.linalg.norm(second.p_world - first.p_world) > 0.01


def test_a_moving_reflector_gives_no_stationary_result(truth):
    cell = SimCell(truth, q_home=Q_POSE, time_scale=1.0)
    fake = LeicaTrackerFake(cell, port=0, initialised=True)
    fake.start()
    try:
        with EmsconTracker(_config(fake)) as tracker:
            cell.start_move(Q_POSE + 0.5, 0.01, 0.1)
            with pytest.raises(MeasurementError, match="reflector moving") as info:
                tracker.measure()
            assert info.value.code == P.ES_RS_NoStationaryResult
            cell.stop()
            assert np.linalg.norm(tracker.measure().p_world - cell.target_world()) < 1e-4
    finally:
        fake.stop()


def test_configuration_errors_name_what_is_wrong(fake):
    with pytest.raises(DeviceFaultError, match=r"no reflector named 'CCR'; the server lists 'RRR 1.5in'"):
        EmsconTracker(_config(fake, reflector="CCR"))
    fake.weather_station = False
    with pytest.raises(DeviceFaultError, match="no weather station"):
        EmsconTracker(_config(fake))
    fake.weather_station = True
    fake.coordinate_system = 6  # ES_CS_SCW: spherical
    with pytest.raises(DeviceFaultError, match="coordinate system type is 6; Recal needs the right-handed cartesian"):
        EmsconTracker(_config(fake))
    fake.coordinate_system = 0
    with EmsconTracker(_config(fake, environment="config", temperature_c=23.0)) as tracker:
        assert tracker.environment == (23.0, 1013.25, 50.0)
    assert fake.environment == (23.0, 1013.25, 50.0)
    for bad, match in (
        ({"port": 0}, "port"),
        ({"timeout_s": 0}, "timeout_s"),
        ({"environment": "sky"}, "environment"),
        ({"measure_time_s": 0}, "measure_time_s"),
    ):
        with pytest.raises(ValueError, match=match):
            EmsconConfig(host="h", **bad)
    assert EmsconConfig.from_endpoint("10.0.0.5:7000").port == 7000
    assert EmsconConfig.from_endpoint("10.0.0.5").port == 700


# --------------------------------------------------------------------------- the beam


def test_a_broken_beam_stays_broken_until_the_reflector_is_found(fake, cell):
    cell.faults.beam_break_at = [2]
    with EmsconTracker(_config(fake)) as tracker:
        tracker.measure()
        for _ in range(2):  # the tracker does not find the reflector by itself
            with pytest.raises(MeasurementError, match="beam broken") as info:
                tracker.measure()
            assert info.value.code == P.ES_RS_MeasurementStatusNotReady
        assert tracker.status() == "beam_broken"
        with pytest.raises(MeasurementError):  # searched too far from the reflector
            tracker.find_reflector(cell.target_world() + [0.3, 0.0, 0.0])
        tracker.find_reflector(cell.target_world() + [0.02, -0.02, 0.01])
        assert tracker.status() == "ready"
        m = tracker.measure()
    assert m.sequence == 2  # the failed measurements took no sequence number
    assert np.all(np.abs(m.p_world - cell.target_world()) < 5 * m.sigma)


def test_the_reflector_brought_back_into_the_beam_is_held_again(fake, cell):
    cell.faults.beam_break_at = [1]
    with EmsconTracker(_config(fake)) as tracker:
        with pytest.raises(MeasurementError):
            tracker.measure()
        cell.start_move(Q_POSE + 0.1, 1.0, 1.0)  # away from the beam ...
        assert tracker.status() == "beam_broken"
        cell.start_move(Q_POSE, 1.0, 1.0)  # ... and back into it
        assert tracker.status() == "ready"
        assert np.all(np.abs(tracker.measure().p_world - cell.target_world()) < 1e-4)


def test_a_reflector_facing_away_breaks_the_beam(truth):
    cell = SimCell(truth, q_home=Q_POSE)
    fake = LeicaTrackerFake(cell, port=0, initialised=True, reflector_axis_tool=(0.0, 0.0, 1.0), acceptance_deg=30.0)
    p = cell.target_world()
    z = cell.T_world_tool()[:3, 2]
    angle = np.degrees(np.arccos(z @ (-p / np.linalg.norm(p))))
    assert (fake.visible() is None) == (angle < 30.0)
    fake.reflector_axis_tool = cell.T_world_tool()[:3, :3].T @ (-p / np.linalg.norm(p))  # aimed at the tracker
    assert fake.visible() is None
    fake.acceptance_deg = 10.0
    tilted = Q_POSE.copy()
    tilted[5] += 0.0
    tilted[4] += np.radians(25.0)  # the wrist turns the reflector 25 degrees away
    cell.start_move(tilted, 1.0, 1.0)
    assert fake.visible() == "the reflector faces away"
    fake.start()
    try:
        with EmsconTracker(_config(fake)) as tracker:
            assert tracker.status() == "beam_broken"
            cell.start_move(Q_POSE, 1.0, 1.0)
            with pytest.raises(MeasurementError):  # facing the tracker again, but nobody pointed at it
                tracker.measure()
            tracker.find_reflector(cell.target_world())
            tracker.measure()
    finally:
        fake.stop()


def test_the_arm_blocks_the_line_of_sight(truth):
    """A pose where the forearm crosses the line from the tracker (the world origin) to the
    reflector: blocked with capsules of 45 mm, clear with a thin arm."""
    cell = SimCell(dataclasses.replace(truth, base=np.array([0.8, 0.0, 0.0, 0.0, 0.0, 0.0])), q_home=np.zeros(6))
    # Upper arm straight up, forearm folded back towards the tracker, reflector beyond it.
    cell.start_move(np.array([np.pi, -np.pi / 2, 0.3, 0.0, 0.0, 0.0]), 1.0, 1.0)
    cell.start_move(np.array([0.0, -np.pi / 2, 0.0, 0.0, 0.0, 0.0]), 1.0, 1.0)
    fake = LeicaTrackerFake(cell, port=0, initialised=True, arm_radius_m=0.045)
    from fakes.leica_tracker import arm_segments, segment_distance

    p = cell.target_world()
    clearance = min(
        segment_distance(np.zeros(3), p * (1 - fake.reflector_clearance_m / np.linalg.norm(p)), a, b)
        for a, b in arm_segments(cell)
    )
    assert (fake.visible() == "the arm blocks the line of sight") == (clearance < 0.045)
    fake.arm_radius_m = max(clearance - 0.01, 0.0)
    assert fake.visible() is None
    fake.arm_radius_m = clearance + 0.01
    assert fake.visible() == "the arm blocks the line of sight"


def test_segment_distance_against_a_dense_sampling():
    rng = np.random.default_rng(0)
    from fakes.leica_tracker import segment_distance

    s = np.linspace(0, 1, 401)
    for _ in range(20):
        a0, a1, b0, b1 = rng.normal(size=(4, 3))
        A = a0 + s[:, None] * (a1 - a0)
        B = b0 + s[:, None] * (b1 - b0)
        brute = np.min(np.linalg.norm(A[:, None] - B[None], axis=2))
        assert segment_distance(a0, a1, b0, b1) == pytest.approx(brute, abs=5e-3)
        assert segment_distance(a0, a1, b0, b1) <= brute + 1e-12


# --------------------------------------------------------------------------- unsolicited and bad packets


class Scripted(LeicaTrackerFake):
    """The fake with extra packets sent before the answer to chosen commands."""

    def __init__(self, cell, before: dict[int, bytes]):
        super().__init__(cell, port=0, initialised=True)
        self.before = before

    def _answer(self, kind, command, packet):  # after the fake counted the command
        extra = self.before.pop(command, None)
        return ([extra] if extra else []) + super()._answer(kind, command, packet)


def _result_packet(x_mm: float) -> bytes:
    return struct.pack("<iIIIi17d", 156, 2, 0, 0, 0, x_mm, x_mm, x_mm, *([0.01] * 4), *([0.0] * 10))


def test_an_unsolicited_result_is_never_returned(cell):
    # a stale result waiting before the measurement: dropped, the fresh one returned
    fake = Scripted(cell, {})
    fake.start()
    try:
        with EmsconTracker(_config(fake)) as tracker:
            for c in fake.clients():
                c.send_raw(_result_packet(99999.0))
            assert select.select([tracker._sock], [], [], 5.0)[0]  # it has reached the driver's socket
            m = tracker.measure()
            assert np.linalg.norm(m.p_world - cell.target_world()) < 1e-4
            # a result inside another command's exchange: a protocol error, then a clean reconnect
            fake.before[122] = _result_packet(99999.0)
            with pytest.raises(ProtocolError, match="unsolicited measurement result while waiting for command 122"):
                tracker.status()
            assert tracker.status() == "ready"
            assert np.linalg.norm(tracker.measure().p_world - cell.target_world()) < 1e-4
    finally:
        fake.stop()


@pytest.mark.parametrize(
    "packet, match",
    [
        (struct.pack("<iII", 12, 77, 0), "unknown type 77"),
        (struct.pack("<iII", 20, 8, 25) + b"\0" * 8, "type 8 with a wrong size 20"),
        (struct.pack("<iIII", 16, 0, 2, 0), "reply to command 2 while waiting for command 49"),
    ],
)
def test_wrong_packets_are_protocol_errors_then_a_full_reconnect(cell, packet, match):
    fake = Scripted(cell, {49: packet})
    fake.start()
    try:
        with EmsconTracker(_config(fake)) as tracker:
            with pytest.raises(ProtocolError, match=match):
                tracker.measure()
            before = cell.counters["emscon.request"]
            m = tracker.measure()
            assert cell.counters["emscon.request"] - before == 10  # full set-up (9 commands) and the measurement
            assert m.sequence == 1 and np.linalg.norm(m.p_world - cell.target_world()) < 1e-4
    finally:
        fake.stop()


class Recording(LeicaTrackerFake):
    """The fake keeping the number of every command it answers."""

    def __init__(self, cell):
        super().__init__(cell, port=0, initialised=True)
        self.commands: list[int] = []

    def _answer(self, kind, command, packet):
        self.commands.append(command)
        return super()._answer(kind, command, packet)


@pytest.mark.parametrize("fault", ["drop_connection_at", "garble_at"])
def test_after_a_dropped_link_the_whole_set_up_runs_again(cell, fault):
    """The fake's state is the instrument's, shared by its connections, so a measurement after a
    reconnect would succeed without a set-up: the commands themselves show that the driver sends
    the whole of it again. A dropped connection is repaired at once (one resend); a malformed
    packet is a ``ProtocolError`` and the next measurement reconnects."""
    fake = Recording(cell)
    fake.start()
    try:
        with EmsconTracker(_config(fake)) as tracker:
            set_up = list(fake.commands)
            assert set_up == [  # no Initialize: the tracker is initialised
                P.ES_C_GetSystemStatus,
                P.ES_C_GetTrackerStatus,
                P.ES_C_SetUnits,
                P.ES_C_GetCoordinateSystemType,
                P.ES_C_GetEnvironmentParams,
                P.ES_C_GetReflectors,
                P.ES_C_SetReflector,
                P.ES_C_SetMeasurementMode,
                P.ES_C_SetStationaryModeParams,
            ]
            fake.commands.clear()
            setattr(cell.faults, fault, [cell.counters["emscon.request"] + 1])
            if fault == "garble_at":
                with pytest.raises(ProtocolError, match="of 23 bytes; expected 16"):
                    tracker.measure()
                assert fake.commands == [P.ES_C_StartMeasurement]
                fake.commands.clear()
            m = tracker.measure()
            assert fake.commands == set_up + [P.ES_C_StartMeasurement]
        assert m.sequence == 1 and np.all(np.abs(m.p_world - cell.target_world()) < 5 * m.sigma)
    finally:
        fake.stop()


def test_no_server_there(fake):
    port = fake.port
    fake.stop()
    with pytest.raises(DeviceConnectionError, match="cannot connect"):
        EmsconTracker(EmsconConfig(host="127.0.0.1", port=port, timeout_s=0.5))


# --------------------------------------------------------------------------- faults across processes

# The set-up of a tracker that is not yet initialised is commands 1-10 (GetSystemStatus,
# GetTrackerStatus, Initialize, SetUnits, GetCoordinateSystemType, GetEnvironmentParams,
# GetReflectors, SetReflector, SetMeasurementMode, SetStationaryModeParams); the first
# StartMeasurement is 11, the second 12. A reconnect's set-up is 9 commands (no Initialize).
FAULTS = {
    "dropped": (("drop_connection_at=12",), None, None, "ready"),
    "dropped-twice": (
        ("drop_connection_at=12,13",),
        DeviceConnectionError,
        r"command 49 failed after one reconnect",
        "ready",
    ),
    "delay": (("delay_at=12", "delay_s=1.0"), DeviceTimeoutError, r"no answer to command 49 within 0\.6 s", "ready"),
    "malformed": (("garble_at=12",), ProtocolError, r"reply to command 49 of 23 bytes; expected 16", "ready"),
    "error-status": (
        ("error_status_at=12",),
        DeviceFaultError,
        r"command 49: the server reports status 36 \(code 36\)",
        "ready",
    ),
    "beam-break": (
        ("beam_break_at=2",),
        MeasurementError,
        r"no reflector locked \(beam broken\) \(code 10004\)",
        "beam_broken",
    ),
}


@pytest.mark.parametrize("name", FAULTS)
def test_faults_of_an_emscon_tracker_in_another_process(fault_cell, cell_truth, name):
    """``recal fake-cell`` with one fault: the first measurement is good, the second fails with
    the driver's error naming the tracker (or, a single dropped connection, is repaired by one
    reconnect with the full set-up), and the driver goes on with fresh measurements."""
    faults, error, match, status_after = FAULTS[name]
    cell = fault_cell(only=("emscon",), faults=faults)
    T = fk(cell_truth, np.zeros((1, 6)))[0]
    expected = T[:3, :3] @ cell_truth.targets["smr1"] + T[:3, 3]
    config = EmsconConfig.from_endpoint(cell.endpoint["emscon"], timeout_s=0.5, measure_time_s=0.1)
    with EmsconTracker(config) as tracker:
        assert np.linalg.norm(tracker.measure().p_world - expected) < 1e-4
        if error is None:
            assert np.linalg.norm(tracker.measure().p_world - expected) < 1e-4
        else:
            with pytest.raises(error, match=match) as info:
                tracker.measure()
            assert f"emScon tracker {cell.endpoint['emscon']}" in str(info.value)
        assert tracker.status() == status_after
        if status_after == "beam_broken":
            tracker.find_reflector(expected)
        m = tracker.measure()
    assert m.sequence == (3 if error is None else 2)
    assert np.all(np.abs(m.p_world - expected) < 5 * m.sigma)


def test_a_result_with_a_bad_status_is_not_a_measurement(cell):
    class BadResult(LeicaTrackerFake):
        def _measure(self):
            answer = super()._measure()
            bad = bytearray(answer[1])
            struct.pack_into("<I", bad, 8, P.ES_RS_NoStationaryResult)  # ReturnDataT.status
            return [answer[0], bytes(bad)]

    fake = BadResult(cell, port=0, initialised=True)
    fake.start()
    try:
        with EmsconTracker(_config(fake)) as tracker:
            with pytest.raises(MeasurementError, match="no stationary result") as info:
                tracker.measure()
            assert info.value.code == P.ES_RS_NoStationaryResult
    finally:
        fake.stop()


class Refusing(LeicaTrackerFake):
    """The fake answering chosen commands, once each, with a reply of the given status."""

    def __init__(self, cell, refuse: dict[int, int]):
        super().__init__(cell, port=0, initialised=True)
        self.refuse = refuse

    def _answer(self, kind, command, packet):
        status = self.refuse.pop(command, None)
        if status is None:
            return super()._answer(kind, command, packet)
        return [struct.pack("<iIII", 16, 0, command, status)]


@pytest.mark.parametrize(
    "status, error, match, reconnects",
    [
        (P.ES_RS_MeasurementStatusNotReady, MeasurementError, "no reflector locked", False),
        (P.ES_RS_ADMStartUpBusy, MeasurementError, "the distance meter is warming up", False),
        (P.ES_RS_NoStationaryResult, MeasurementError, "reflector moving", False),
        (P.ES_RS_SensorNotStable, MeasurementError, "the tracker is not stable", False),
        (P.ES_RS_SystemNotReadyForMeasurement, MeasurementError, "not ready to measure", False),
        (P.ES_RS_NotImplemented, ProtocolError, "rejected by the server", True),
        (P.ES_RS_WrongParameter1, ProtocolError, "rejected by the server", True),
        (P.ES_RS_Parameter1OutOfRangeNOK, ProtocolError, "rejected by the server", True),
        (P.ES_RS_NoTrackerConnected, DeviceFaultError, "the server reports status 38", False),
    ],
)
def test_each_status_of_a_measurement_maps_onto_the_exception_tree(cell, status, error, match, reconnects):
    """The codes the driver knows, as cesapi numbers them: what cannot be measured now is a
    ``MeasurementError`` (the link kept), what the server does not take is a ``ProtocolError``
    (then a full set-up), anything else a ``DeviceFaultError``; each with its code."""
    fake = Refusing(cell, {P.ES_C_StartMeasurement: status})
    fake.start()
    try:
        with EmsconTracker(_config(fake)) as tracker:
            with pytest.raises(error, match=match) as info:
                tracker.measure()
            assert type(info.value) is error and info.value.code == status
            assert f"emScon tracker 127.0.0.1:{fake.port}" in str(info.value)
            before = cell.counters["emscon.request"]
            m = tracker.measure()
            assert cell.counters["emscon.request"] - before == (10 if reconnects else 1)  # set-up (9) or none
        assert np.all(np.abs(m.p_world - cell.target_world()) < 5 * m.sigma) and m.sequence == 1
    finally:
        fake.stop()


def test_a_tracker_that_lost_its_initialisation_is_initialised_again(fake, cell):
    """The tracker restarted under the driver (its processor no longer initialised): the
    measurement is a ``DeviceFaultError`` with ``ES_RS_TrackerNotInitialized``, and the next one
    reconnects, initialises and measures."""
    with EmsconTracker(_config(fake)) as tracker:
        tracker.measure()
        fake.initialised = False
        assert tracker.status() == "not_initialised"
        with pytest.raises(DeviceFaultError, match="the tracker is not initialised") as info:
            tracker.measure()
        assert type(info.value) is DeviceFaultError and info.value.code == P.ES_RS_TrackerNotInitialized
        before = cell.counters["emscon.request"]
        m = tracker.measure()
        assert cell.counters["emscon.request"] - before == 11  # the set-up with Initialize (10), the measurement
        assert fake.initialised and tracker.status() == "ready"
    assert m.sequence == 2 and np.all(np.abs(m.p_world - cell.target_world()) < 5 * m.sigma)


def test_status_changes_reach_every_client_and_a_closing_server_means_a_reconnect(cell):
    fake = Scripted(cell, {})
    fake.start()
    try:
        with EmsconTracker(_config(fake)) as a, EmsconTracker(_config(fake)) as b:
            cell.faults.beam_break_at = [1]
            with pytest.raises(MeasurementError):
                a.measure()
            assert a.beam_lost and not b.beam_lost
            assert b.status() == "beam_broken" and b.beam_lost  # the status change, then the reply
            b.find_reflector(cell.target_world())
            assert not b.beam_lost
            fake.before[122] = struct.pack("<iII", 12, 8, 998)  # ES_SSC_ServerClosing in the exchange
            before = cell.counters["emscon.request"]
            assert b.status() == "ready"
            assert cell.counters["emscon.request"] - before == 11  # the status, a full set-up (9), the status again
    finally:
        fake.stop()


# The set-up of a tracker that is not initialised, in the order the driver sends it.
SET_UP_NOT_INITIALISED = (
    "GetSystemStatus",
    "GetTrackerStatus",
    "Initialize",
    "SetUnits",
    "GetCoordinateSystemType",
    "GetEnvironmentParams",
    "GetReflectors",
    "SetReflector",
    "SetMeasurementMode",
    "SetStationaryModeParams",
)


@pytest.mark.parametrize("fault", ["garble_at", "drop_connection_at", "error_status_at"])
@pytest.mark.parametrize("step", range(1, len(SET_UP_NOT_INITIALISED) + 1), ids=SET_UP_NOT_INITIALISED)
def test_a_fault_at_any_step_of_the_set_up_ends_promptly_and_the_next_connect_works(cell, fault, step):
    """Issue 22: a garbled reply to ``Initialize`` (its size field 7 bytes too large) held the
    driver for ``initialize_timeout_s`` waiting for bytes that never come, and a session stayed
    ``running`` for two minutes. A packet's body follows its header at once, so a wrong size is a
    ``ProtocolError`` within ``PACKET_BODY_S`` at every step; a drop or an error status is the
    tree's error at once. The next connect (the session retries opening) sets the tracker up."""
    from drivers.leica_emscon import PACKET_BODY_S

    fake = LeicaTrackerFake(cell, port=0, initialised=False, initialize_time_s=0.0)
    fake.start()
    try:
        setattr(cell.faults, fault, [step])
        config = _config(fake, timeout_s=5.0, initialize_timeout_s=120.0)
        started = time.monotonic()
        try:
            tracker = EmsconTracker(config)
        except (ProtocolError, DeviceFaultError, DeviceConnectionError) as exc:
            if fault == "garble_at":
                assert isinstance(exc, ProtocolError), exc  # a size too large, or bytes of the next packet
            tracker = EmsconTracker(config)
        elapsed_s = time.monotonic() - started
        with tracker:
            m = tracker.measure()
        assert np.all(np.abs(m.p_world - cell.target_world()) < 5 * m.sigma)
        # promptly: well inside one ordinary reply deadline, never the 120 s of Initialize
        assert elapsed_s < config.timeout_s, (elapsed_s, PACKET_BODY_S)
    finally:
        fake.stop()
