"""Bench acquisition: device profiles, frame codecs, transports, turntable
drivers, the session runner behind ``calib record`` and the emulator behind
``calib emulate`` (docs/acquisition.md)."""
