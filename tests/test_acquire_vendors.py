"""The shipped vendor profiles against byte sequences from the vendors' documents
and from established open-source drivers (each test names its source), with the
documented values, checksums and scale factors; and one corrupted byte seen
rejected and counted. Checksums of the vendor frames are checked by the decoder
itself: a frame whose checksum fails would not decode."""

import struct

import numpy as np
import pytest

from calib_cli.acquire.codec import AsciiDecoder, BinaryDecoder, SampleStream
from calib_cli.acquire.device import render
from calib_cli.acquire.profile import G0, load_imu_profile, parse_imu_profile

D2R = np.pi / 180


def decode(name_or_prof, data: bytes):
    prof = load_imu_profile(name_or_prof) if isinstance(name_or_prof, str) else name_or_prof
    dec = (BinaryDecoder if prof.format == "binary" else AsciiDecoder)(prof)
    items = dec.feed(data)
    st = SampleStream(prof)
    return prof, items, st.push(items, 0.0), st


def corrupt_counted(prof, frame: bytes, at: int):
    """Frame, frame with byte ``at`` flipped, frame: the middle one is rejected
    and counted as one checksum error between two accepted frames."""
    bad = bytearray(frame)
    bad[at] ^= 0x5A
    dec = (BinaryDecoder if prof.format == "binary" else AsciiDecoder)(prof)
    items = dec.feed(frame) + dec.feed(bytes(bad)) + dec.feed(frame)
    assert [it is None for it in items] == [False, True, False]
    return items


# -- Xsens MTi -----------------------------------------------------------------
# Scottapotamas/xsens-mti, test/test_xsens_mti_parse_messages.c, test_parse_mdata2_full:
# an MTData2 packet captured from an MTi-300 with MT Manager (its docs/mtmanager_packets.md
# "Packet Example 4"), with the values MT Manager decoded.
XSENS_FULL = bytes.fromhex(
    "FA FF 36 92 10 20 02 91 8D 10 60 04 01 36 3F A6 20 10 10 3F 35 E0 42 3F 31 CD 15 BD 9F 49"
    " DB BD A9 38 CF 40 20 0C BD 63 5A 90 41 1D 08 D4 3E 5F AA 50 40 10 0C B9 11 68 00 3C C9 01"
    " 00 3A 0F 7D 00 40 30 0C BC 3B 29 80 3C 35 FC 00 3C A4 6E 00 80 20 0C 3C AE A2 41 BB 56 D8"
    " 00 BA D5 AC 01 80 30 10 3F 80 00 00 37 DF 88 01 B6 89 80 00 B6 08 C0 00 C0 20 0C BE FB FB"
    " F2 3F 33 C4 85 BF A0 A2 C1 08 10 04 42 16 80 00 30 10 04 00 01 86 E1 E0 20 04 00 40 00 03"
    " DD")


def test_xsens_mtdata2_capture_decodes_to_mt_manager_values():
    prof, items, rows, _ = decode("xsens-mti", XSENS_FULL)
    assert len(items) == 1 and items[0] is not None
    names = [f.name for f in prof.fields]
    it = dict(zip(names, items[0], strict=True))
    assert it["counter"] == 37261 and it["stf"] == 20332454
    np.testing.assert_allclose(rows[0, 2:5], [-0.05550629, 9.81465530, 0.21842313], atol=5e-8)
    np.testing.assert_allclose(rows[0, 5:8], [0.02131760, -0.00327826, -0.00163019], atol=5e-9)
    assert rows[0, 8] == 37.625


def test_xsens_corrupt_byte_rejected_and_counted():
    prof = load_imu_profile("xsens-mti")
    corrupt_counted(prof, XSENS_FULL, 40)


def test_xsens_commands_match_the_documented_bytes():
    # the same repository's docs/mtmanager_packets.md lists the bytes MT Manager wrote and
    # read: GoToConfig FA FF 30 00 D1, its ack FA FF 31 00 D0, GoToMeasurement
    # FA FF 10 00 F1, its ack FA FF 11 00 F0
    prof = load_imu_profile("xsens-mti")
    cfg, start = prof.configure[0], prof.start_steps[0]
    assert render(prof, cfg.send, False, "frame", {}) == bytes.fromhex("FA FF 30 00 D1")
    assert render(prof, cfg.expect, False, "frame", {}) == bytes.fromhex("FA FF 31 00 D0")
    assert render(prof, start.send, False, "frame", {}) == bytes.fromhex("FA FF 10 00 F1")
    assert render(prof, start.expect, False, "frame", {}) == bytes.fromhex("FA FF 11 00 F0")
    # SetOutputConfiguration as written by MT Manager (12 outputs), checksum 0x99
    body = ("FA FF C0 30 10 20 FF FF 10 60 FF FF 20 10 01 90 40 20 01 90 40 10 01 90 40 30 01 90"
            " 80 20 01 90 80 30 01 90 C0 20 00 64 08 10 00 0A 30 10 00 32 E0 20 FF FF")
    assert render(prof, body, False, "frame", {})[-1] == 0x99
    # our configuration at 400 Hz: 0x0190 per output
    out = render(prof, prof.configure[1].send, False, "frame", {"rate": 400})
    assert out[4:8] == bytes.fromhex("10 20 FF FF") and out[12:16] == bytes.fromhex("40 20 01 90")
    assert sum(out[1:]) % 256 == 0


# -- VectorNav VN-100 binary -----------------------------------------------------
# UWOrbital/OBC-firmware, the VN-100 binary parsing gtest (TestVn100PackUnpack): a VN-100
# packet, group 1, fields 0x0528 (YawPitchRoll, AngularRate, Accel, MagPres), CRC C0 E9.
VN_HEADER = bytes.fromhex("FA 01 28 05")
VN_PAYLOAD = bytes.fromhex(
    "A8 02 C3 3F E7 89 B0 42 3D A9 6A C1 D0 83 54 3A 92 3E 0B BB 1C 25 30 BA 04 7D 1C 41 3B B2"
    " 83 3D 4E EA 9C BE F1 BD 93 BE A4 55 8C BD 26 C7 77 3E F4 28 E6 41 57 CE C1 42")
VN_FRAME = VN_HEADER + VN_PAYLOAD + bytes.fromhex("C0 E9")


def _vn_profile_like_capture():
    """The shipped profile's frame, checksum and group mechanism with the capture's
    outputs (YawPitchRoll, AngularRate, Accel, MagPres; the shipped one has TimeStartup
    and the uncompensated Imu): the header is computed from the fields' group and bit."""
    text = load_imu_profile("vectornav-vn100").raw_text
    text = text[:text.index("[sequence]")]
    outs = [("yaw", 3, ""), ("pitch", 3, ""), ("roll", 3, ""), ("gx", 5, "rad/s"),
            ("gy", 5, "rad/s"), ("gz", 5, "rad/s"), ("ax", 8, "m/s^2"), ("ay", 8, "m/s^2"),
            ("az", 8, "m/s^2"), ("mx", 10, ""), ("my", 10, ""), ("mz", 10, ""),
            ("temp", 10, "degC"), ("pres", 10, "")]
    text += "".join(f'[[field]]\nname = "{n}"\ntype = "f32"\ngroup = 1\nbit = {b}\n'
                    f'unit = "{u}"\n' for n, b, u in outs)
    return parse_imu_profile(text, "vn-capture.toml")


def test_vectornav_binary_group1_capture():
    prof = _vn_profile_like_capture()
    assert prof.sync == VN_HEADER  # FA, group 1, mask 0x0528 (little-endian)
    _, items, rows, _ = decode(prof, VN_FRAME)
    assert len(items) == 1 and items[0] is not None
    v = struct.unpack("<14f", VN_PAYLOAD)
    np.testing.assert_allclose(rows[0, 2:5], v[6:9])  # Accel, m/s^2 (9.78 m/s^2 on x)
    np.testing.assert_allclose(rows[0, 5:8], v[3:6])  # AngularRate, rad/s
    assert abs(rows[0, 8] - 28.77) < 1e-3  # MagPres temperature, degC


def test_vectornav_binary_corrupt_byte_rejected_and_counted():
    corrupt_counted(_vn_profile_like_capture(), VN_FRAME, 20)


def test_vectornav_shipped_header_and_register_75():
    prof = load_imu_profile("vectornav-vn100")
    assert prof.sync == bytes.fromhex("FA 01 01 06")  # bits 0, 9, 10 of group 1
    st = prof.start_steps[0]
    cmd = render(prof, st.send, True, "nmea", {"rate": 400, "div": 2})
    assert cmd.startswith(b"$VNWRG,75,1,2,01,0601*") and cmd.endswith(b"\r\n")


# -- VectorNav $VNIMU --------------------------------------------------------------
# $VNIMU sentences captured from a VectorNav VN-200 (same message as the VN-100): one quoted
# in S. Bruder's VectorNav MATLAB readers (checksum *66), one in a vn200 driver's cgreen test
# (checksum 0x6D); magnetic field (gauss), accel (m/s^2), gyro (rad/s), temp, pressure.
VNIMU = [b"$VNIMU,-00.0350,+00.4222,-00.6643,-00.015,+00.019,+09.948,+00.002066,-00.008442,"
         b"-00.044656,+20.7,+084.322*66\r\n",
         b"$VNIMU,+01.0854,-02.0143,+02.1980,-01.157,+00.271,-09.847,+00.001114,+00.000727,"
         b"+00.002568,+21.4,+084.334*6D\r\n"]


def test_vnimu_sentences_decode():
    _, items, rows, _ = decode("vectornav-vnimu", b"".join(VNIMU))
    assert all(it is not None for it in items) and len(rows) == 2
    np.testing.assert_allclose(rows[0, 2:9], [-0.015, 0.019, 9.948, 0.002066, -0.008442,
                                              -0.044656, 20.7])
    np.testing.assert_allclose(rows[1, 2:5], [-1.157, 0.271, -9.847])


def test_vnimu_corrupt_byte_rejected_and_counted():
    prof = load_imu_profile("vectornav-vnimu")
    bad = VNIMU[0].replace(b"+09.948", b"+09.958")
    dec = AsciiDecoder(prof)
    items = dec.feed(VNIMU[0] + bad + VNIMU[1])
    assert [it is None for it in items] == [False, True, False]
    st = SampleStream(prof)
    st.push(items, 0.0)
    assert st.counts["checksum_errors"] == 1


# -- MicroStrain MIP ---------------------------------------------------------------
# ArduPilot/ardupilot, AP_ExternalAHRS_LORD (its first version's test packet): a 3DM-GX5
# IMU data packet, scaled accel 0x04, scaled gyro 0x05, GPS correlation timestamp 0x12,
# Fletcher checksum 1D 37.
MIP_ARDUPILOT = bytes([
    0x75, 0x65, 0x80, 0x2a, 0x0e, 0x04, 0x3e, 0x49, 0x56, 0x65, 0xbb, 0x24, 0x12, 0xc0, 0xbf,
    0x7a, 0xa0, 0x1d, 0x0e, 0x05, 0xbb, 0xc7, 0x35, 0x1d, 0xbb, 0x22, 0xce, 0x02, 0x3b, 0x0e,
    0xf6, 0x1a, 0x0e, 0x12, 0x40, 0x5c, 0x1a, 0xb0, 0x20, 0xc4, 0x9b, 0xa6, 0x00, 0x00, 0x00,
    0x06, 0x1d, 0x37])
# LORD-MicroStrain/mip_sdk, the packet example (create_packet_from_buffer): reference time
# 0xD5, its delta 0xD6, scaled accel, scaled gyro, delta theta 0x07, delta velocity 0x08.
MIP_SDK = bytes.fromhex(
    "75 65 80 4c 0a d5 00 00 00 05 5e e6 7c c0 0a d6 00 00 00 01 4e 43 4a 00 0e 04 3d 9e e8 8d"
    " 38 7f db 00 bf 7a af 03 0e 05 bb 0c 1e 30 bb 57 2e 68 bb aa 24 ae 0e 07 bc 8a ac 80 bc 72"
    " c5 0e bc c4 e2 c1 0e 08 3e ee 3d 9f bd 66 da dd c0 af de f5 91 96")


def test_mip_gx5_packet_decodes():
    prof, items, rows, _ = decode("microstrain-gx5", MIP_ARDUPILOT)
    assert items[0] is not None
    acc = struct.unpack(">3f", MIP_ARDUPILOT[6:18])
    gyr = struct.unpack(">3f", MIP_ARDUPILOT[20:32])
    np.testing.assert_allclose(rows[0, 2:5], np.array(acc) * G0)  # g -> m/s^2
    np.testing.assert_allclose(rows[0, 5:8], gyr)
    it = dict(zip([f.name for f in prof.fields], items[0], strict=True))
    assert it["tow"] == struct.unpack(">d", MIP_ARDUPILOT[34:42])[0] and it["time_flags"] == 6
    assert abs(rows[0, 4] / G0 + 0.979) < 1e-3  # about -1 g on z: the unit at rest


def test_mip_sdk_example_packet_checksum_and_fields():
    # our profile asks for 0x12 time stamps: the SDK example (reference time 0xD5) is a
    # packet without them; with the time stamp made the 0xD5 record it decodes
    text = load_imu_profile("microstrain-gx5").raw_text
    text = text.replace("modulus = 604800             # the time of week rolls over weekly\n"
                        "counts_per_s = 1", "counts_per_s = 1e9").replace("modulus = 604800", "")
    text = text.replace('name = "tow"\ntype = "f64"\ntag = 0x12', 'name = "tow"\ntype = "u64"\n'
                        'tag = 0xD5').replace('type = "u16"\ntag = 0x12', 'type = "u16"\n'
                                              'tag = 0xD5\noptional = true')
    text = text.replace('unit = "s"\n', 'unit = "ns"\n')
    prof = parse_imu_profile(text, "gx5-sdk.toml")
    _, items, rows, _ = decode(prof, MIP_SDK)
    assert items[0] is not None
    acc = struct.unpack(">3f", MIP_SDK[26:38])
    np.testing.assert_allclose(rows[0, 2:5], np.array(acc) * G0)
    assert abs(rows[0, 4] / G0 + 0.979) < 1e-3


def test_mip_corrupt_byte_rejected_and_counted():
    corrupt_counted(load_imu_profile("microstrain-gx5"), MIP_ARDUPILOT, 10)


def test_mip_commands_fletcher():
    # the DCP manual's Ping 75 65 01 02 02 01 E0 C6 and Set to Idle ... 02 02 E1 C7
    prof = load_imu_profile("microstrain-gx5")
    assert render(prof, prof.identify[0].send, False, "frame", {}) == \
        bytes.fromhex("75 65 01 02 02 01 E0 C6")
    assert render(prof, prof.configure[0].send, False, "frame", {}) == \
        bytes.fromhex("75 65 01 02 02 02 E1 C7")


# -- Epson M-G370 ---------------------------------------------------------------------
# No captured burst is public: the frame is written byte by byte from the data sheet's
# burst layout (0x80, ND_FLAGS, TEMP, gyro, accel, COUNT, CHECKSUM, 0x0D; 32-bit outputs)
# with raw values whose documented meaning is checked: gyro 1/66 deg/s and accel 0.4 mg a
# 16-bit step (Epson's UART driver: gyro_sf_dps = 1/66, accl_sf_mg = 1/2.5), so 66 * 65536
# counts are 1 deg/s and 2.5 * 65536 counts 1 mg; the temperature 25 degC at 2634 * 65536.
def _epson_frame(temp, gyro, accel, count):
    words = struct.pack(">H", 0x7E00) + struct.pack(">i", temp) + struct.pack(">3i", *gyro) \
        + struct.pack(">3i", *accel) + struct.pack(">H", count)
    chk = sum(struct.unpack(f">{len(words) // 2}H", words)) & 0xFFFF  # 16-bit word sum
    return b"\x80" + words + struct.pack(">H", chk) + b"\x0D"


def test_epson_burst_scale_factors():
    frame = _epson_frame(2634 * 65536, (66 * 65536, -33 * 65536, 0),
                         (int(2.5 * 65536 * 1000), 0, -int(2.5 * 65536 * 500)), 7)
    assert len(frame) == 36
    prof, items, rows, _ = decode("epson-g370", frame)
    assert items[0] is not None
    np.testing.assert_allclose(rows[0, 2:5], [G0, 0, -0.5 * G0], rtol=1e-9)  # 1000 mg, -500 mg
    np.testing.assert_allclose(rows[0, 5:8], [D2R, -0.5 * D2R, 0], rtol=1e-9)
    assert abs(rows[0, 8] - 25.0) < 1e-4


def test_epson_corrupt_byte_rejected_and_counted():
    frame = _epson_frame(0, (1, 2, 3), (4, 5, 6), 9)
    corrupt_counted(load_imu_profile("epson-g370"), frame, 12)


# -- Safran STIM300 -------------------------------------------------------------------
# No captured datagram is public: written byte by byte from datasheet TS1524 rev. 31,
# Table 5-20 (content), 5.5.7 (CRC over the datagram and 2 dummy zero bytes for 0x93,
# Table 5-22) and 7.5.2.2 (2^14 counts = 1 deg/s; 10 g range: 2^19 counts = 1 g); the CRC
# by a bitwise implementation of the datasheet's polynomial and seed.
def _crc32_stim(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for b in data:
        crc ^= b << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7) & 0xFFFFFFFF if crc & 0x80000000 else \
                (crc << 1) & 0xFFFFFFFF
    return crc


def _i24(v):
    return (v & 0xFFFFFF).to_bytes(3, "big")


def _stim_93(gyro, acc, counter):
    body = b"\x93" + b"".join(_i24(v) for v in gyro) + b"\x00" + \
        b"".join(_i24(v) for v in acc) + b"\x00" + _i24(0) * 3 + b"\x00" + bytes([counter]) \
        + (506).to_bytes(2, "big")
    return body + _crc32_stim(body + b"\x00\x00").to_bytes(4, "big")


def test_stim300_datagram_93_scale_factors_and_crc():
    dg = _stim_93((2**14, -2**13, 0), (0, 0, -(2**19)), 225)
    assert len(dg) == 38
    prof, items, rows, _ = decode("safran-stim300", dg)
    assert items[0] is not None
    np.testing.assert_allclose(rows[0, 5:8], [D2R, -0.5 * D2R, 0])
    np.testing.assert_allclose(rows[0, 2:5], [0, 0, -G0])
    assert prof.checksum.compute(dg[:-4]) == _crc32_stim(dg[:-4] + b"\x00\x00")


def test_stim300_identifier_decides_content():
    # 0x91: rate and acceleration, 24 bytes before the CRC: no dummy byte
    body = b"\x91" + _i24(2**14) * 3 + b"\x00" + _i24(2**19) * 3 + b"\x00" + b"\x05\x01\xfa"
    dg = body + _crc32_stim(body).to_bytes(4, "big")
    _, items, rows, _ = decode("safran-stim300", dg + _stim_93((0, 0, 0), (0, 0, 0), 6))
    assert len(rows) == 2
    np.testing.assert_allclose(rows[0, 2:5], [G0] * 3)


def test_stim300_corrupt_byte_rejected_and_counted():
    dg = _stim_93((1, 2, 3), (4, 5, 6), 1)
    corrupt_counted(load_imu_profile("safran-stim300"), dg, 5)


# -- the counters ------------------------------------------------------------------------
def test_clock_counters_count_lost_frames():
    """STIM300's counter runs at 2000 counts/s: at 500 Hz it steps by 4; a lost datagram
    is a step of 8 (one gap)."""
    prof = load_imu_profile("safran-stim300").with_rate(500.0)
    dgs = b"".join(_stim_93((0, 0, 0), (0, 0, 0), c % 256) for c in (250, 254, 2, 10, 14))
    st = SampleStream(prof)
    rows = st.push(BinaryDecoder(prof).feed(dgs), 0.0)
    assert len(rows) == 5 and st.counts["gaps"] == 1
    np.testing.assert_allclose(np.diff(rows[:, 0]), [0.002, 0.002, 0.004, 0.002])


def test_profile_sequence_of_1000_fields_and_odd_values_refused():
    """issue 37, points 10 and 15: rate_hz nan/inf/1e300/true, bits = "16", and 1000
    fields are exit 3 naming the file and key, never an internal error."""
    from calib_cli.errors import InputError

    base = load_imu_profile("generic-bin6").raw_text
    for bad, key in (("rate_hz = nan", "rate_hz"), ("rate_hz = inf", "rate_hz"),
                     ("rate_hz = 1e300", "rate_hz"), ("rate_hz = true", "rate_hz"),
                     ('rate_hz = "1000"', "rate_hz")):
        with pytest.raises(InputError, match=key) as ei:
            parse_imu_profile(base.replace("rate_hz = 1000", bad), "p.toml")
        assert ei.value.path == "p.toml"
    with pytest.raises(InputError, match="sequence.bits"):
        parse_imu_profile(base.replace("bits = 16", 'bits = "16"'), "p.toml")
    many = base + "".join(f'[[field]]\nname = "x{i}"\ntype = "i32"\n' for i in range(1000))
    with pytest.raises(InputError, match="field"):
        parse_imu_profile(many, "p.toml")


# -- a CAN IMU from a DBC file (cantools) -----------------------------------------------
# SAE J1939-71 scaling of ARI/ACCS (the OpenIMU300ZI J1939 manual's): 0x7D00 = 32000 is
# zero rate (32000 / 128 - 250) and zero acceleration (32000 * 0.01 - 320); +9.81 m/s^2 is
# 32981 = 0x80D5, +1 deg/s is 32128 = 0x7D80; little-endian (Intel) signals.
def test_j1939_dbc_messages_decode():
    from calib_cli.acquire.codec import CanAssembler

    prof = load_imu_profile("j1939-imu")
    asm = CanAssembler(prof)
    items = asm.feed_message(0x0CF02A80, bytes.fromhex("80 7D 00 7D 00 7D 00 00"))
    items += asm.feed_message(0x08F02D80, bytes.fromhex("00 7D 00 7D D5 80 00 00"))
    rows = SampleStream(prof).push(items, 0.0)
    np.testing.assert_allclose(rows[0, 2:5], [0, 0, 9.81], atol=1e-9)
    np.testing.assert_allclose(rows[0, 5:8], [0, D2R, 0], atol=1e-12)  # pitch rate is gy
    # a truncated frame is rejected and counted; a foreign id is ignored
    assert asm.feed_message(0x08F02D80, b"\x00\x7d") == [None]
    assert asm.feed_message(0x123, b"\x00" * 8) == [] and asm.foreign == 1
    # without a counter, an ARI twice in a row (its ACCS lost) is one lost sample
    ari = bytes.fromhex("00 7D 00 7D 00 7D 00 00")
    assert asm.feed_message(0x0CF02A80, ari) == []
    assert asm.feed_message(0x0CF02A80, ari) == [None]
