"""The log writers the tests use: calib's own (calib_cli/io/log_writers.py,
written from the formats' published specifications, vectorised so that
``calib simulate --out LOG.ulg|.bin|.mcap|.bag`` and the benchmarks can use
them), checked against the independent readers pyulog, pymavlink and rosbags
in tests/test_log_formats.py."""

from calib_cli.io.log_writers import (  # noqa: F401
    write_dataflash,
    write_mcap,
    write_ros1_bag,
    write_ros2_bag,
    write_ulog,
)
