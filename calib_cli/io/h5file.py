"""Writing calib's HDF5 files so that they are checksummed whole and an I/O
error never reaches HDF5 (issue 37; docs/file-formats.md, "Integrity").

- ``h5_output(path)``: an ``h5py.File`` on a temporary file beside ``path``
  that replaces it on success (io/outpath.py: lock, umask, no leftovers).
  HDF5 writes through ``_Sink``, a file object that never reports an error
  to HDF5: it keeps the first OSError (a full disk, EIO, a quota) and drops
  the writes after it, so HDF5 closes every object in order and its state
  stays clean (before, h5py raised "Can't decrement id ref count" and the
  interpreter died of a segmentation fault at exit). The context then ends
  in ``OutputError`` (exit 2) naming ``path``; the temporary file is removed.
- ``put``: every dataset of one element or more gets a Fletcher-32 checksum
  (text as fixed-length UTF-8, whose bytes the checksum covers; HDF5 keeps
  variable-length strings on a heap no checksum covers).
- ``set_text``: text attributes as fixed-length UTF-8 up to ``TEXT_ATTR_MAX``
  bytes (HDF5 checksums them with their object header, format 1.10); longer
  text as a one-element string dataset of the same name beside them, with
  Fletcher-32 (``validate.text`` reads either, and the older layouts).
"""

from __future__ import annotations

import contextlib
import os

import h5py
import numpy as np

# the file format of HDF5 1.10: checksummed superblock, object headers and chunk indexes
LIBVER = ("v110", "v110")
TEXT_ATTR_MAX = 2048  # bytes; longer attribute values go where no checksum covers them


class _Sink:
    """A file for h5py's ``fileobj`` driver that never fails towards HDF5 (see above)."""

    def __init__(self, path, mode: str):
        flags = os.O_RDWR | (os.O_CREAT | os.O_TRUNC if mode == "w" else 0)
        self.fd = os.open(path, flags, 0o600)
        self.pos = 0
        self.size = os.fstat(self.fd).st_size
        self.error: OSError | None = None

    def seek(self, off, whence=0):
        self.pos = off if whence == 0 else self.pos + off if whence == 1 else self.size + off
        return self.pos

    def tell(self):
        return self.pos

    def readinto(self, buf):
        mv = memoryview(buf).cast("B")
        got = 0
        if self.error is None:
            try:
                data = os.pread(self.fd, len(mv), self.pos)
                mv[:len(data)] = data
                got = len(data)
            except OSError as exc:
                self.error = exc
        mv[got:] = bytes(len(mv) - got)  # past the end (or after an error): zeros
        self.pos += len(mv)
        return len(mv)

    def read(self, n=-1):
        buf = bytearray(max(0, self.size - self.pos) if n is None or n < 0 else n)
        self.readinto(buf)
        return bytes(buf)

    def write(self, data):
        mv = memoryview(data).cast("B")
        if self.error is None:
            done = 0
            try:
                while done < len(mv):
                    done += os.pwrite(self.fd, mv[done:], self.pos + done)
            except OSError as exc:
                self.error = exc
        self.pos += len(mv)
        self.size = max(self.size, self.pos)
        return len(mv)

    def truncate(self, size=None):
        size = self.pos if size is None else size
        if self.error is None:
            try:
                os.ftruncate(self.fd, size)
            except OSError as exc:
                self.error = exc
        self.size = size
        return size

    def flush(self):
        pass

    def close(self):
        if self.fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = -1


@contextlib.contextmanager
def h5_writer(path, mode: str = "w", name=None):
    """An ``h5py.File`` writing ``path`` (mode "w" or "r+") through ``_Sink``;
    an I/O error ends in OutputError (exit 2) naming ``name`` (default ``path``)."""
    from calib_cli.io.outpath import write_error

    sink = _Sink(path, mode)
    h5 = None
    try:
        h5 = h5py.File(sink, mode, libver=LIBVER) if mode == "w" else h5py.File(sink, mode)
        yield h5
        h5.close()
    except BaseException:
        if h5 is not None:
            with contextlib.suppress(Exception):
                h5.close()
        sink.close()
        if sink.error is not None:  # the cause of whatever HDF5 said after it
            raise write_error(sink.error, name or path) from None
        raise
    sink.close()
    if sink.error is not None:
        raise write_error(sink.error, name or path)


@contextlib.contextmanager
def h5_output(path):
    """Write the HDF5 file ``path`` atomically (see the module docstring)."""
    from calib_cli.io.outpath import atomic_file

    with atomic_file(path) as tmp, h5_writer(tmp, "w", name=str(path)) as h5:
        yield h5


# ---------------------------------------------------------------------------
# datasets and text, checksummed


def _fixed_text(values) -> tuple[np.ndarray, object]:
    enc = [str(v).encode("utf-8", "backslashreplace") for v in values]
    n = max([1] + [len(b) for b in enc])
    dt = h5py.string_dtype("utf-8", n)  # the array carries it too: HDF5 converts no ASCII
    return np.array(enc, dtype=dt), dt


def put(group, name: str, data, chunks=True, **kw):
    """A dataset with a Fletcher-32 checksum (text as fixed-length UTF-8).
    A scalar or empty array has nothing HDF5 can filter and is written as is."""
    dtype = kw.pop("dtype", None)
    if isinstance(data, (list, tuple)) and data and all(isinstance(v, str) for v in data) \
            or (dtype is not None and h5py.check_string_dtype(np.dtype(dtype)) is not None):
        data, dtype = _fixed_text(list(data))
    arr = np.asarray(data)
    if arr.dtype.kind == "U":
        arr, dtype = _fixed_text(arr.ravel().tolist())
    if arr.ndim >= 1 and arr.size >= 1:
        return group.create_dataset(name, data=arr, dtype=dtype, chunks=chunks,
                                    fletcher32=True, **kw)
    return group.create_dataset(name, data=arr, dtype=dtype, **kw)


def set_text(obj, name: str, text) -> None:
    """A text attribute (see the module docstring for where long text goes)."""
    b = str(text).encode("utf-8", "backslashreplace")
    if len(b) <= TEXT_ATTR_MAX:
        dt = h5py.string_dtype("utf-8", max(1, len(b)))
        obj.attrs.create(name, np.array(b, dtype=dt), dtype=dt)
        return
    if name in obj.attrs:
        del obj.attrs[name]
    if name in obj:
        del obj[name]
    dt = h5py.string_dtype("utf-8", len(b))
    obj.create_dataset(name, data=np.array([b], dtype=dt), dtype=dt, chunks=(1,),
                       fletcher32=True)


def set_attrs(obj, values: dict) -> None:
    """Attributes: text through ``set_text``, numbers and arrays as they are."""
    for k, v in values.items():
        if isinstance(v, str):
            set_text(obj, k, v)
        else:
            obj.attrs[k] = v
