"""The real serial driver against the virtual interferometer over a real pty and over TCP (socket://), lock-step."""

from __future__ import annotations

import math
import time

import pytest

from stagectl.drivers.base import DeviceState, FaultKind
from stagectl.drivers.interferometer import InterferometerConfig, SerialInterferometer
from stagectl.errors import ConfigError, DriverError, DriverInitError
from stagectl.schema import load
from stagectl.sim.interferometer import SimInterferometer, SimInterferometerConfig

RES_M = 1e-9


class ScriptedPlant:
    """Minimal plant with the StagePlant sensor interface: a deterministic trajectory."""

    def __init__(self) -> None:
        self.t_s = 0.0
        self.x_m = 0.0

    def step(self, dt_s: float) -> None:
        self.t_s += dt_s
        # 5 mm amplitude sine plus a slow drift: exercises sign changes and sub-count fractions
        self.x_m = 5e-3 * math.sin(2 * math.pi * 3.0 * self.t_s) + 1e-4 * self.t_s + 0.37e-9

    def measure(self) -> float:
        return self.x_m


@pytest.fixture(params=["pty", "tcp"])
def transport(request):
    return request.param


def make_sim(transport, tmp_path, plant, **kw) -> SimInterferometer:
    link = str(tmp_path / "ifm0") if transport == "pty" else None
    return SimInterferometer(plant, SimInterferometerConfig(transport=transport, link_path=link,
                                                            resolution_m=RES_M, **kw))


@pytest.fixture
def rig(transport, tmp_path):
    plant = ScriptedPlant()
    sim = make_sim(transport, tmp_path, plant)
    dut = SerialInterferometer(InterferometerConfig(url=sim.url, resolution_m=RES_M, max_step_m=1e-4))
    dut.set_pump(sim.pump)
    dut.open()
    dut.configure()
    dut.enable()
    yield plant, sim, dut
    dut.close()
    sim.close()


def cycle(plant, dut):
    plant.step(1e-3)
    return dut.read()


def test_url_forms(transport, tmp_path):
    with make_sim(transport, tmp_path, ScriptedPlant()) as sim:
        if transport == "pty":
            assert sim.url == str(tmp_path / "ifm0")
            assert (tmp_path / "ifm0").is_symlink()
        else:
            assert sim.url.startswith("socket://127.0.0.1:") and not sim.url.endswith(":0")
    assert not (tmp_path / "ifm0").exists()


def test_1000_lockstep_cycles_equal_quantised_plant(rig):
    plant, sim, dut = rig
    for _ in range(1000):
        m = cycle(plant, dut)
        assert m.fresh and m.fault is None
        assert m.counts == round(plant.measure() / RES_M) == sim.last_counts
        assert m.position_m == m.counts * RES_M
        assert abs(m.position_m - plant.measure()) <= RES_M / 2 + 1e-18
    s = dut.stats
    assert (s.frames, s.crc_errors, s.sequence_gaps, s.bytes_discarded) == (1000, 0, 0, 0)
    assert dut.last_frame is not None and dut.last_frame.seq == 999
    assert dut.last_frame.timestamp_ns == round(plant.t_s * 1e9)
    dut.disable()
    assert dut.state is DeviceState.CONFIGURED


FAULTS = [
    # (inject kwargs, driver fault kind)
    (dict(kind="corrupt", count=3), FaultKind.CRC_ERRORS),
    (dict(kind="drop", count=1), FaultKind.SEQUENCE_GAP),
    (dict(kind="signal_lost"), FaultKind.SENSOR_ERROR),
    (dict(kind="laser_unlocked"), FaultKind.SENSOR_ERROR),
    (dict(kind="glitch", glitch_m=2e-6), FaultKind.SENSOR_ERROR),
    (dict(kind="glitch", glitch_m=1e-3, flag=False), FaultKind.SENSOR_ERROR),  # caught by max_step_m
    (dict(kind="stop", count=50), FaultKind.MISSED_FRAME),
    (dict(kind="disconnect"), FaultKind.DISCONNECTED),
]


@pytest.mark.parametrize("inject,kind", FAULTS, ids=[f"{i['kind']}{'-noflag' if 'flag' in i else ''}" for i, _ in FAULTS])
def test_injected_fault_detected_within_3_cycles(rig, inject, kind):
    plant, sim, dut = rig
    for _ in range(10):
        assert cycle(plant, dut).fault is None
    sim.inject(**inject)
    seen = []
    for _ in range(3):
        m = cycle(plant, dut)
        seen.append(m.fault)
        if m.fault is not None:
            break
    assert seen[-1] is not None, f"{inject} not detected in 3 cycles"
    assert seen[-1].kind is kind, seen
    assert dut.fault is not None and dut.fault.kind is kind
    assert dut.state is DeviceState.FAULT


def test_low_signal_threshold(transport, tmp_path):
    plant = ScriptedPlant()
    with make_sim(transport, tmp_path, plant) as sim:
        with SerialInterferometer(InterferometerConfig(url=sim.url, min_signal=50)) as dut:
            dut.set_pump(sim.pump)
            dut.configure()
            assert cycle(plant, dut).fault is None
            sim.inject("low_signal", signal=20)
            m = cycle(plant, dut)
            assert m.fault is not None and m.fault.kind is FaultKind.SENSOR_ERROR and "20/255" in m.fault.detail


def test_garbage_is_resynchronised_without_fault(rig):
    plant, sim, dut = rig
    sim.inject("garbage", count=20, garbage_bytes=13)
    for _ in range(30):
        m = cycle(plant, dut)
        assert m.fresh and m.counts == sim.last_counts
    assert dut.stats.bytes_discarded >= 20 * 13 - 20 * 2  # a trailing A5 may be held, then dropped
    assert dut.fault is None


def test_transient_fault_clears_with_fault_reset(rig):
    plant, sim, dut = rig
    cycle(plant, dut)
    sim.inject("signal_lost", count=2)
    assert cycle(plant, dut).fault.kind is FaultKind.SENSOR_ERROR
    cycle(plant, dut)
    dut.fault_reset()
    assert dut.state is DeviceState.CONFIGURED
    m = cycle(plant, dut)
    assert m.fault is None and m.fresh and m.counts == sim.last_counts


def test_scripted_faults_from_config_mapping(transport, tmp_path):
    data = {"transport": transport, "resolution_m": RES_M, "faults": [{"kind": "drop", "at_frame": 5, "count": 2}]}
    if transport == "pty":
        data["link_path"] = str(tmp_path / "ifm-yaml")
    cfg = load(SimInterferometerConfig, data, path="interferometer_sim")
    plant = ScriptedPlant()
    with SimInterferometer(plant, cfg) as sim, SerialInterferometer(
        load(InterferometerConfig, {"url": sim.url, "max_sequence_gap": 1}, path="serial")
    ) as dut:
        dut.set_pump(sim.pump)
        dut.configure()
        kinds = [cycle(plant, dut).fault for _ in range(8)]
    assert kinds[:5] == [None] * 5
    assert kinds[7] is not None and kinds[7].kind is FaultKind.SEQUENCE_GAP and "2 frames missing" in kinds[7].detail


def test_config_errors_name_the_key():
    with pytest.raises(ConfigError) as ei:
        load(InterferometerConfig, {"url": "x", "resolution_m": -1, "stale_cyles": 3}, path="serial")
    msg = str(ei.value)
    assert "serial.resolution_m: must be > 0 m" in msg and "serial.stale_cyles: unknown key" in msg
    with pytest.raises(ConfigError, match="interferometer_sim.faults\\[0\\].kind"):
        load(SimInterferometerConfig, {"faults": [{"kind": "explode"}]}, path="interferometer_sim")


def test_plant_time_lockstep_emits_one_frame_per_elapsed_period(tmp_path):
    plant = ScriptedPlant()
    with make_sim("pty", tmp_path, plant, rate_hz=500.0, lockstep="plant_time") as sim:
        with SerialInterferometer(InterferometerConfig(url=sim.url, resolution_m=RES_M, stale_cycles=2)) as dut:
            dut.set_pump(sim.pump)
            dut.configure()
            fresh = [cycle(plant, dut).fresh for _ in range(20)]  # 1 kHz loop, 500 Hz sensor
    # first read at t = 1 ms gets the t = 0 sample; then one sample per 2 ms (t = 2, 4, ... 20 ms)
    assert fresh == [True, True] + [False, True] * 9
    assert sim.seq == 11


def test_close_idempotent_and_read_after_close(transport, tmp_path):
    with make_sim(transport, tmp_path, ScriptedPlant()) as sim:
        dut = SerialInterferometer(InterferometerConfig(url=sim.url))
        with dut:
            assert dut.state is DeviceState.OPEN
        dut.close()
        dut.close()
        assert dut.state is DeviceState.CLOSED
        with pytest.raises(DriverError):
            dut.read()
    sim.close()
    sim.close()


@pytest.mark.parametrize("url", ["/nonexistent/stagectl-ifm", "socket://127.0.0.1:1", "bogus://x"])
def test_bad_url_gives_driver_init_error_naming_it(url):
    dut = SerialInterferometer(InterferometerConfig(url=url))
    with pytest.raises(DriverInitError, match=url.replace("/", ".")):
        dut.open()
    assert dut.state is DeviceState.CLOSED


def test_disconnect_mid_stream_reports_disconnected_not_exception(rig):
    plant, sim, dut = rig
    held = cycle(plant, dut).counts
    sim.disconnect()
    m = cycle(plant, dut)
    assert m.fault is not None and m.fault.kind is FaultKind.DISCONNECTED and not m.fresh
    assert m.counts == held  # last good value held


def test_disconnect_persists_through_a_fault_reset(rig):
    """A closed port never comes back: persisting_faults() names it (so the loop refuses a reset) before and
    after the device-level fault reset, while a fault whose cause is gone (a CRC burst) does not persist."""
    plant, sim, dut = rig
    sim.inject(kind="corrupt", count=3)
    for _ in range(3):
        cycle(plant, dut)
    assert dut.fault is not None and dut.fault.kind is FaultKind.CRC_ERRORS
    assert dut.persisting_faults() == ()
    dut.fault_reset()
    assert cycle(plant, dut).fault is None
    sim.disconnect()
    assert cycle(plant, dut).fault.kind is FaultKind.DISCONNECTED
    (cause,) = dut.persisting_faults()
    assert cause.startswith("disconnected: port ") and "restart the daemon" in cause
    dut.fault_reset()
    assert dut.persisting_faults() == (cause,)
    assert cycle(plant, dut).fault.kind is FaultKind.DISCONNECTED  # and it is still dead


def test_streaming_thread_delivers_contiguous_frames(transport, tmp_path):
    """Real-time mode: the sim thread streams; the consumer waits on select (timeouts are only guards)."""
    plant = ScriptedPlant()
    plant.step(0.01)
    with make_sim(transport, tmp_path, plant, rate_hz=2000.0) as sim:
        with SerialInterferometer(InterferometerConfig(url=sim.url, resolution_m=RES_M)) as dut:
            dut.configure()
            sim.start()
            frames = []
            guard = time.monotonic() + 10.0
            while len(frames) < 200 and time.monotonic() < guard:
                frames += dut.read_frames(0.5)
            sim.stop()
    assert len(frames) >= 200
    seqs = [f.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    assert all(f.counts == round(plant.measure() / RES_M) for f in frames)
    assert all(f.timestamp_ns <= dut.last_rx_ns for f in frames)


def test_1000_cycles_against_the_real_stage_plant(transport, tmp_path):
    """The real StagePlant (viscous stage, noisy quantised sensor) driven by a force sine."""
    from stagectl.sim.plant import PlantConfig, StagePlant

    plant = StagePlant(PlantConfig.from_mapping({
        "mass_kg": 2.0,
        "friction": {"model": "stribeck", "fc_n": 0.0, "fs_n": 0.0, "viscous_n_s_m": 20.0},
        "sensor": {"resolution_m": RES_M, "noise_std_m": 3e-9},
        "seed": 7,
    }))
    with make_sim(transport, tmp_path, plant) as sim, SerialInterferometer(
        InterferometerConfig(url=sim.url, resolution_m=RES_M)
    ) as dut:
        dut.set_pump(sim.pump)
        dut.configure()
        dut.enable()
        moved = 0
        for k in range(1000):
            plant.step(2.0 * math.sin(2 * math.pi * 5.0 * k * 1e-3), 1e-3)
            m = dut.read()
            assert m.fresh and m.fault is None
            assert m.counts == plant.measure_counts()
            moved = max(moved, abs(m.counts))
        assert moved > 1000  # the stage really moved (µm scale), so the comparison is not trivial
        assert dut.last_frame.timestamp_ns == round(plant.t_s * 1e9)


class _NoCountPump:
    """A world-style pump: runs the sim but returns something that is not LinkBytes (a message count)."""

    def __init__(self, sim, ret):
        self.sim, self.ret = sim, ret

    def __call__(self):
        self.sim.pump()
        return self.ret


@pytest.mark.parametrize("ret", [None, 0, 3])
def test_pump_without_link_bytes_waits_for_one_new_frame(transport, tmp_path, ret):
    plant = ScriptedPlant()
    with make_sim(transport, tmp_path, plant) as sim, SerialInterferometer(
        InterferometerConfig(url=sim.url, resolution_m=RES_M)
    ) as dut:
        dut.set_pump(_NoCountPump(sim, ret))
        dut.configure()
        for _ in range(200):
            m = cycle(plant, dut)
            assert m.fresh and m.counts == sim.last_counts and m.fault is None


def test_reader_that_opens_late_gets_current_contiguous_frames(tmp_path):
    """The device streamed into a pty nobody read until the kernel buffer was full: the device keeps no
    backlog of its own, so after the driver's configure (input flush) the frames are current and contiguous
    (no SEQUENCE_GAP from stale queued frames followed by fresh ones)."""
    plant = ScriptedPlant()
    with make_sim("pty", tmp_path, plant) as sim:
        for _ in range(5000):  # 140 kB: far more than a pty buffers (~20 kB here)
            plant.step(1e-3)
            sim.pump()
        assert sim.bytes_sent < 5000 * 28  # the link stopped taking bytes
        with SerialInterferometer(InterferometerConfig(url=sim.url, resolution_m=RES_M)) as dut:
            dut.set_pump(sim.pump)
            dut.configure()
            for k in range(20):
                m = cycle(plant, dut)
                assert m.fault is None, (k, m.fault)
                if k >= 2:  # at most the tail of one torn frame may precede the first full frame
                    assert m.fresh and m.counts == sim.last_counts
            assert dut.stats.sequence_gaps == 0


def test_rx_timeout_waits_for_a_triggered_frame(transport, tmp_path):
    """Real time, device triggered by the loop (``trigger: sync``): with ``rx_timeout_s`` read() waits for the
    frame instead of returning the previous one. The trigger fires once read() is waiting (no sleeps)."""
    import threading

    plant = ScriptedPlant()
    with make_sim(transport, tmp_path, plant, trigger="sync") as sim, SerialInterferometer(
        InterferometerConfig(url=sim.url, resolution_m=RES_M, rx_timeout_s=5.0)
    ) as dut:
        dut.configure()
        waiting = threading.Event()
        recv = dut._recv

        def spy(timeout_s):
            if timeout_s > 0:
                waiting.set()
            return recv(timeout_s)

        dut._recv = spy
        for _ in range(3):
            waiting.clear()
            plant.step(1e-3)
            t = threading.Thread(target=lambda: waiting.wait(5.0) and sim.trigger())
            t.start()
            m = dut.read()
            t.join()
            assert m.fresh and m.counts == round(plant.measure() / RES_M) and m.fault is None


def test_backlog_burst_after_silence_is_fresh_and_true_silence_still_faults(transport, tmp_path):
    """A SYNC-triggered device held off the CPU (a loaded sim-plant) answers its backlog of triggers in one burst:
    the read that gets it takes the newest frame, fresh, no sequence gap and no fault, and the silent reads
    before it (49 of ``stale_cycles`` 50) did not fault. A device that then stays silent for 50 reads faults
    MISSED_FRAME on exactly the 50th. Lock-step: the pump returns the bytes the device wrote (none while silent),
    so the frame timing is controlled, with no wall-clock wait."""
    from stagectl.drivers.interferometer_protocol import LinkBytes

    plant = ScriptedPlant()
    with make_sim(transport, tmp_path, plant, trigger="sync") as sim, SerialInterferometer(
        InterferometerConfig(url=sim.url, resolution_m=RES_M, stale_cycles=50)
    ) as dut:
        backlog = [0]  # triggers not answered yet
        answer = [True]

        def pump() -> LinkBytes:
            plant.step(1e-3)
            backlog[0] += 1
            if not answer[0]:
                return LinkBytes(0)
            n = sum(int(sim.trigger()) for _ in range(backlog[0]))
            backlog[0] = 0
            return LinkBytes(n)

        dut.set_pump(pump)
        dut.configure()
        for _ in range(5):
            assert dut.read().fresh
        answer[0] = False
        for k in range(49):
            m = dut.read()
            assert not m.fresh and m.fault is None, k
        answer[0] = True
        m = dut.read()  # 50 frames at once
        assert m.fresh and m.fault is None and m.counts == sim.last_counts
        assert dut.stats.sequence_gaps == 0 and dut.last_frame is not None and dut.last_frame.seq == sim.seq - 1
        answer[0] = False
        for k in range(49):
            assert dut.read().fault is None, k
        m = dut.read()
        assert m.fault is not None and m.fault.kind is FaultKind.MISSED_FRAME and "50 cycles" in m.fault.detail
