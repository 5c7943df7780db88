"""issue 37, points 10 and 15, through the commands: a profile with rate_hz nan, inf,
1e300 or true, bits = "16", or a binary frame of 1000 fields is exit 3 with one line
naming the file and the key (never exit 70, never accepted)."""

import pytest

from calib_cli.acquire.profile import load_imu_profile
from tests.test_acquire_e2e import _calib

BASE = load_imu_profile("generic-bin6").raw_text


def test_emulate_and_record_refuse_rate_nan(tmp_path):
    """The repro: exit 3 and one line naming the file and the key (the real process)."""
    p = tmp_path / "p.toml"
    p.write_text(BASE.replace("rate_hz = 1000", "rate_hz = nan"))
    for args in (["emulate", "--imu", str(p), "--duration", "0.1"],
                 ["record", "--imu", str(p), "--port", str(tmp_path / "nope"), "--duration",
                  "1", "--out", str(tmp_path / "o.h5")]):
        r = _calib(*args)
        assert r.returncode == 3, (args, r.stderr)
        lines = [x for x in r.stderr.splitlines() if x.strip()]
        assert len(lines) == 1 and str(p) in lines[0] and "rate_hz" in lines[0], r.stderr
    assert not (tmp_path / "o.h5").exists()


@pytest.mark.parametrize("bad", ["rate_hz = inf", "rate_hz = 1e300", "rate_hz = true",
                                 'rate_hz = "1000"', "rate_hz = -5"])
def test_emulate_and_record_refuse_a_bad_rate(tmp_path, bad):
    from calib_cli.errors import InputError
    from tests.test_acquire_e2e import _cli

    p = tmp_path / "p.toml"
    p.write_text(BASE.replace("rate_hz = 1000", bad))
    for args in (["emulate", "--imu", str(p), "--duration", "0.1"],
                 ["record", "--imu", str(p), "--port", str(tmp_path / "nope"), "--duration",
                  "1", "--out", str(tmp_path / "o.h5")]):
        r = _cli(*args)
        assert isinstance(r.exception, InputError), (args, r.output)
        assert r.exception.path == str(p) and "rate_hz" in r.exception.message
    assert not (tmp_path / "o.h5").exists()


def test_bits_as_string_and_1000_fields_refused(tmp_path):
    from calib_cli.errors import InputError
    from tests.test_acquire_e2e import _cli

    p = tmp_path / "p.toml"
    p.write_text(BASE.replace("bits = 16", 'bits = "16"'))
    r = _cli("emulate", "--imu", str(p), "--duration", "0.1")
    assert isinstance(r.exception, InputError)
    assert "sequence.bits must be an integer" in r.exception.message
    p.write_text(BASE + "".join(f'[[field]]\nname = "x{i}"\ntype = "i32"\n' for i in range(1000)))
    r = _calib("emulate", "--imu", str(p), "--duration", "0.1")  # the repro: the real process
    assert r.returncode == 3 and "field" in r.stderr and "Traceback" not in r.stderr
    p.write_text(BASE + "".join(f'[[field]]\nname = "x{i}"\ntype = "i32"\n' for i in range(80)))
    r = _cli("emulate", "--imu", str(p), "--duration", "0.1")  # 352 bytes: no u8 length
    assert isinstance(r.exception, InputError)
    assert "does not fit a u8 length" in r.exception.message


@pytest.mark.parametrize("bad", ["timeout_s = true", 'timeout_s = "60"', "timeout_s = nan"])
def test_table_profile_numbers_are_numbers(bad):
    from calib_cli.acquire.profile import load_table_profile, parse_table_profile
    from calib_cli.errors import InputError

    text = open(load_table_profile("generic-3axis").path).read()
    with pytest.raises(InputError, match="timeout_s"):
        parse_table_profile(text.replace("timeout_s = 60", bad), "t.toml")
