"""Codec tests against golden byte vectors written by hand from public
documentation (CRC catalogue check values, published NMEA sentences, the
Modbus RTU example frame) and from the shipped profiles' documented layouts,
with checksums computed by independent code (the standard library's
binascii/zlib, a bitwise reference CRC-8), never by our encoder."""

import binascii
import zlib

import numpy as np
import pytest

from calib_cli.acquire.checksum import NAMED_CRCS, Crc, additive, crc_from_spec, xor8
from calib_cli.acquire.codec import AsciiDecoder, BinaryDecoder, CanAssembler, SampleStream
from calib_cli.acquire.profile import G0, load_imu_profile, parse_imu_profile
from calib_cli.errors import InputError

CHECK = b"123456789"
D2R = np.pi / 180


@pytest.mark.parametrize("name", sorted(NAMED_CRCS))
def test_crc_catalogue_check_values(name):
    w, p, i, ri, ro, xo, check = NAMED_CRCS[name]
    c = Crc(w, p, i, ri, ro, xo)
    assert c.compute_table(CHECK) == check  # the generic table-driven path
    assert c.compute(CHECK) == check  # with the stdlib fast path where it applies


def test_crc_check_values_hand_written():
    # values from the public CRC catalogue, typed here, not taken from NAMED_CRCS
    assert crc_from_spec({"width": 16, "poly": 0x1021, "init": 0xFFFF}).compute(CHECK) == 0x29B1
    assert crc_from_spec({"width": 32, "poly": 0x04C11DB7, "init": 0xFFFFFFFF, "refin": True,
                          "refout": True, "xorout": 0xFFFFFFFF}).compute_table(CHECK) == 0xCBF43926
    assert crc_from_spec({"width": 16, "poly": 0x8005, "init": 0xFFFF, "refin": True,
                          "refout": True}).compute(CHECK) == 0x4B37
    assert crc_from_spec({"width": 8, "poly": 0x07}).compute(CHECK) == 0xF4
    assert zlib.crc32(CHECK) == 0xCBF43926 and binascii.crc_hqx(CHECK, 0xFFFF) == 0x29B1


def test_simple_checksums():
    assert xor8(CHECK) == 0x31
    assert additive(CHECK) == 0xDD  # 0x31 + ... + 0x39 = 0x1DD


def test_modbus_rtu_example_frame():
    # the classic Modbus RTU request "read 10 holding registers from 0":
    # 01 03 00 00 00 0A C5 CD, CRC-16/MODBUS sent low byte first
    frame = bytes.fromhex("01 03 00 00 00 0A C5 CD")
    crc = crc_from_spec({"name": "crc-16/modbus"}).compute(frame[:-2])
    assert crc.to_bytes(2, "little") == frame[-2:]


NMEA = [b"$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\r\n",
        b"$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A\r\n"]

GGA_PATTERN = (r"GPGGA,(?P<ax>[\d.]+),(?P<ay>[\d.]+),N,(?P<az>[\d.]+),E,"
               r"(?P<gx>\d),(?P<gy>\d+),(?P<gz>[\d.]+),.*")
GGA_PROFILE = r'''
format = "ascii"
rate_hz = 1
[frame]
pattern = 'PATTERN'
[checksum]
kind = "xor"
[[field]]
name = "ax"
[[field]]
name = "ay"
[[field]]
name = "az"
[[field]]
name = "gx"
[[field]]
name = "gy"
[[field]]
name = "gz"
'''.replace("PATTERN", GGA_PATTERN)


def test_nmea_published_checksums():
    for s in NMEA:
        body = s[1:s.index(b"*")]
        assert xor8(body) == int(s[s.index(b"*") + 1:][:2], 16)
    dec = AsciiDecoder(parse_imu_profile(GGA_PROFILE))
    items = dec.feed(b"garbage" + NMEA[0] + NMEA[1])
    assert items[0] == (123519.0, 4807.038, 1131.0, 1.0, 8.0, 0.9)
    assert items[1] is None  # an RMC sentence: good checksum, but not this pattern
    bad = NMEA[0].replace(b"*47", b"*46")
    assert dec.feed(bad) == [None]


# generic-bin6, written byte by byte from the layout documented in the profile
BIN6_PAYLOAD = bytes.fromhex("0201 40420F00 00000000 18FCFFFF 40420F00 40420F00 00000000"
                             " FFFFFFFF C409")
BIN6_FRAME = bytes.fromhex("AA55 20") + BIN6_PAYLOAD + bytes.fromhex("444C")


def test_bin6_golden_frame():
    assert binascii.crc_hqx(BIN6_FRAME[2:-2], 0xFFFF) == 0x444C  # independent CRC
    prof = load_imu_profile("generic-bin6")
    assert prof.frame_size == len(BIN6_FRAME) == 37
    dec = BinaryDecoder(prof)
    items = dec.feed(b"\x00\xAA\x13" + BIN6_FRAME[:10])
    assert items == []
    items = dec.feed(BIN6_FRAME[10:] + BIN6_FRAME)
    assert len(items) == 2
    st = SampleStream(prof)
    rows = st.push(items, 0.0)
    # seq 0x0102 -> gap from 0x0102 to 0x0102 is a duplicate; the first row:
    t, seq = rows[0, :2]
    assert seq == 0x0102 and t == 0.0
    np.testing.assert_allclose(rows[0, 2:], [0, -1e-3 * G0, G0, D2R, 0, -1e-6 * D2R, 25.0],
                               rtol=1e-12, atol=1e-15)
    assert st.counts["duplicates"] == 1


def test_bin6_bad_crc_counted_once_and_resync():
    prof = load_imu_profile("generic-bin6")
    frames = []
    for seq in range(6):
        pl = bytearray(BIN6_PAYLOAD)
        pl[0:2] = seq.to_bytes(2, "little")
        body = bytes([0x20]) + bytes(pl)
        frames.append(b"\xAA\x55" + body + binascii.crc_hqx(body, 0xFFFF).to_bytes(2, "big"))
    bad = bytearray(frames[1])
    bad[10] ^= 0x40  # payload corruption
    # 1: bad CRC; 2: cut short (checked against the next bytes: a bad CRC too);
    # a false header in garbage (rejected, but no frame lost behind it); 4: dropped
    stream = frames[0] + bytes(bad) + frames[2][:-1] + b"\xAA\x55\x20garbage" + frames[3] \
        + frames[5]
    st = SampleStream(prof)
    dec = BinaryDecoder(prof)
    rows = np.concatenate([st.push(dec.feed(stream[k:k + 7]), 0.0)
                           for k in range(0, len(stream), 7)])
    assert list(rows[:, 1]) == [0, 3, 5]
    assert st.counts["checksum_errors"] == 2  # frames 1 and 2
    assert st.counts["spurious_rejects"] == 1  # the false header
    assert st.counts["gaps"] == 1  # frame 4
    assert st.counts["frames"] == 3


def crc8_bitwise(data):
    c = 0
    for x in data:
        c ^= x
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
    return c


def test_can_golden_messages():
    acc = bytes.fromhex("05 1027 F0D8 0000 04")
    gyr = bytes.fromhex("05 6400 9CFF 0000 D6")
    assert crc8_bitwise(acc[:7]) == 0x04 and crc8_bitwise(gyr[:7]) == 0xD6
    prof = load_imu_profile("can-imu")
    asm = CanAssembler(prof)
    assert asm.feed_message(0x180, acc) == []
    assert asm.feed_message(0x7FF, b"\x00") == []  # another node's message: ignored
    items = asm.feed_message(0x181, gyr)
    st = SampleStream(prof)
    rows = st.push(items, 0.0)
    np.testing.assert_allclose(rows[0, 2:], [G0, -G0, 0, D2R, -D2R, 0], rtol=1e-12)
    assert asm.feed_message(0x180, acc[:7] + b"\x05") == [None]


def test_nmea_imu_profile_sentence():
    body = b"PIMU,65535,0.100000,-0.200000,9.806650,0.001000,-0.002000,0.000500,24.50"
    s = b"$" + body + b"*" + f"{xor8(body):02X}".encode() + b"\r\n"
    prof = load_imu_profile("nmea-imu")
    st = SampleStream(prof)
    dec = AsciiDecoder(prof)
    body2 = body.replace(b"65535", b"1")
    s2 = b"$" + body2 + b"*" + f"{xor8(body2):02x}".encode() + b"\r\n"
    rows = st.push(dec.feed(s + s2), 0.0)
    np.testing.assert_allclose(rows[0, 2:], [0.1, -0.2, 9.80665, 1e-3, -2e-3, 5e-4, 24.5])
    assert rows[1, 1] - rows[0, 1] == 2  # counter rolled over 65535 -> 0 -> 1
    assert st.counts["gaps"] == 1
    np.testing.assert_allclose(rows[1, 0] - rows[0, 0], 2 / prof.rate_hz)


def test_rimu18_fixed_frame_crc32():
    prof = load_imu_profile("rimu18")
    vals = np.arange(18, dtype="<f4")
    body = b"\xA5\x5A" + (7).to_bytes(2, "little") + vals.tobytes()
    frame = body + zlib.crc32(body).to_bytes(4, "little")
    st = SampleStream(prof)
    rows = st.push(BinaryDecoder(prof).feed(frame), 0.0)
    assert len(prof.channels) == 18 and rows.shape == (1, 20)
    np.testing.assert_array_equal(rows[0, 2:], np.arange(18))


def test_profile_errors_name_problem():
    with pytest.raises(InputError, match="format"):
        parse_imu_profile('rate_hz = 1\nformat = "morse"', "x.toml")
    with pytest.raises(InputError, match="unknown CRC"):
        parse_imu_profile(GGA_PROFILE.replace('kind = "xor"', 'kind = "crc"\nname = "crc-99"'))
    with pytest.raises(InputError, match="ax ay az gx gy gz"):
        parse_imu_profile('format = "ascii"\nrate_hz = 1\n' + "".join(
            f'[[field]]\nname = "{n}"\n' for n in ("ax", "ay", "az", "gx", "gy", "zz")))
