"""`calib record --imu auto` / `calib profiles --probe PORT`: the right protocol for each
emulated device (passively from its stream, or by its identification request when it
does not stream), and "no known protocol" on a port that sends noise."""

import os
import subprocess
import sys
import threading
import tty

import pytest

from calib_cli.acquire.emulator import Emulator
from calib_cli.acquire.probe import candidate_profiles, probe_port
from calib_cli.acquire.profile import load_imu_profile

SERIAL = ["xsens-mti", "vectornav-vn100", "vectornav-vnimu", "microstrain-gx5", "epson-g370",
          "safran-stim300", "generic-bin6", "nmea-imu"]


@pytest.fixture(scope="module")
def cands():
    return candidate_profiles()


@pytest.mark.parametrize("name", SERIAL)
def test_passive_probe_names_the_protocol(tmp_path, name, cands):
    prof = load_imu_profile(name)
    em = Emulator(prof, rate=min(prof.rate_hz, 400), link_dir=str(tmp_path)).start()
    try:
        found = probe_port(em.paths["imu"], cands, listen_s=0.4)
    finally:
        em.stop()
    assert found and found[0].name == name and found[0].how == "passive"


@pytest.mark.parametrize("name", ["xsens-mti", "microstrain-gx5", "vectornav-vn100",
                                  "epson-g370"])
def test_identify_request_when_the_unit_is_silent(tmp_path, name, cands):
    em = Emulator(load_imu_profile(name), link_dir=str(tmp_path))
    em.responder.streaming = False  # in configuration mode: nothing streams
    em.start()
    try:
        found = probe_port(em.paths["imu"], cands, listen_s=0.2)
    finally:
        em.stop()
    # a VN-100 answers the same model query whichever output (binary, ASCII) it is set to
    same_unit = {"vectornav-vn100": ["vectornav-vn100", "vectornav-vnimu"]}
    assert [f.name for f in found] == same_unit.get(name, [name])
    assert found[0].how == "identify"


class NoisePort:
    """A pty that sends random bytes until stopped."""

    def __init__(self, link):
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.slave = slave
        os.symlink(os.ttyname(slave), link)
        self.link = link
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self.stop.wait(0.005):
            try:
                os.write(self.master, os.urandom(256))
            except OSError:
                pass

    def close(self):
        self.stop.set()
        self.thread.join(2)
        os.close(self.master)
        os.close(self.slave)


def test_noise_is_no_known_protocol(tmp_path, cands):
    noise = NoisePort(str(tmp_path / "noise"))
    try:  # the real process: exit 3 and the message
        r = subprocess.run([sys.executable, "-m", "calib_cli", "profiles", "--probe",
                            noise.link], capture_output=True, text=True, timeout=120)
    finally:
        noise.close()
    assert r.returncode == 3 and "no known protocol" in r.stderr
    assert "Traceback" not in r.stderr


def test_cli_probe_and_record_auto(tmp_path):
    prof = load_imu_profile("xsens-mti")
    em = Emulator(prof, link_dir=str(tmp_path)).start()
    try:
        r = subprocess.run([sys.executable, "-m", "calib_cli", "profiles", "--probe",
                            em.paths["imu"]], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        assert r.stdout.startswith("xsens-mti: ")
        out = tmp_path / "raw.h5"
        r = subprocess.run([sys.executable, "-m", "calib_cli", "record", "--imu", "auto",
                            "--port", em.paths["imu"], "--duration", "1", "--out", str(out)],
                           capture_output=True, text=True, timeout=120)
    finally:
        em.stop()
    assert r.returncode == 0, r.stderr
    assert "--imu auto: xsens-mti" in r.stderr
    import json

    import h5py

    from calib_cli.io.validate import text

    with h5py.File(out) as h5:  # what the recorder set on the unit and read back
        acq = h5["acquisition"]  # text as checksummed fixed-length UTF-8 (io/h5file.py)
        assert text(acq, "imu_profile", out) == "xsens-mti" and acq.attrs["rate_hz"] == 400
        rb = json.loads(text(acq, "readback", out))
        assert rb["output_configuration"].startswith("FA FF C1 14")
        assert any("GoToMeasurement" in line for line in json.loads(text(acq, "exchange", out)))
