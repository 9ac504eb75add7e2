"""Writes the MATLAB v7.3 test files beside this script (run once; the files
are committed, so the tests need neither Python nor libhdf5):

    pip install h5py numpy && python stages/tests/data/make_mat73.py

A v7.3 MAT-file is HDF5 behind a 512-byte user block that holds MATLAB's
128-byte text header. Each variable is a root dataset whose `MATLAB_class`
attribute names its class; MATLAB writes the dimensions reversed (HDF5's C
order over the reversed shape is MATLAB's column-major order), compresses
large arrays in deflated chunks, stores `char` as `uint16`, complex arrays as
a compound of `real` and `imag`, an empty array as its dimensions with
`MATLAB_empty = 1`, a struct as a group, and the targets of cell
references under `#refs#`. The values are those of `val` in
stages/tests/io_files.rs (`math.sin`, as Rust's `f64::sin`, from the C
library), so the tests compare them exactly.
"""

import math
import pathlib

import h5py
import numpy as np

HERE = pathlib.Path(__file__).resolve().parent


def val(trial, x, k):
    return 1.75 + 0.01 * trial + 0.1 * x + math.sin(k * 0.37) / 3.0


def stack(trials, taxels, samples):
    """MATLAB `data(sample, taxel, trial)` as a NumPy array of that shape."""
    a = np.empty((samples, taxels, len(trials)))
    for j, t in enumerate(trials):
        for x in range(taxels):
            for k in range(samples):
                a[k, x, j] = val(t, x, k)
    return a


def header():
    text = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Tue Dec  1 12:00:00 2026 HDF5 schema 1.00 ."
    h = text.ljust(116, b" ") + b"\0" * 8 + (0x0200).to_bytes(2, "little") + b"IM"
    return h.ljust(512, b"\0")


def variable(f, name, matlab_array, cls, chunked=False):
    """A numeric MATLAB variable: the array stored reversed, as MATLAB does."""
    data = np.ascontiguousarray(np.asarray(matlab_array).T)
    kw = dict(chunks=True, compression="gzip", compression_opts=3) if chunked else {}
    d = f.create_dataset(name, data=data, **kw)
    d.attrs.create("MATLAB_class", np.bytes_(cls))
    return d


def mat73(path, fill):
    with h5py.File(path, "w", userblock_size=512, libver="earliest") as f:
        fill(f)
    with open(path, "r+b") as fh:
        fh.write(header())


def stack_file(f):
    variable(f, "fs", np.array([[1000.0]]), "double")
    variable(f, "data", stack([0, 1], 4, 25), "double", chunked=True)
    variable(f, "angle_deg", np.array([[40.0, 70.0]]), "double")
    # Passed over, as the v5 reader passes over non-numeric variables.
    note = f.create_dataset("note", data=np.frombuffer("edge".encode("utf-16-le"), dtype="<u2").reshape(4, 1))
    note.attrs.create("MATLAB_class", np.bytes_("char"))
    note.attrs.create("MATLAB_int_decode", np.int32(2))
    meta = f.create_group("meta")
    meta.attrs.create("MATLAB_class", np.bytes_("struct"))
    variable(meta, "gain", np.array([[2.0]]), "double")
    empty = f.create_dataset("unused", data=np.array([0, 0], dtype="<u8"))
    empty.attrs.create("MATLAB_class", np.bytes_("double"))
    empty.attrs.create("MATLAB_empty", np.uint8(1))
    refs = f.create_group("#refs#")
    refs.create_dataset("a", data=np.array([0, 0], dtype="<u8"))


def int16_file(f):
    # ADC counts as a logger saves them: int16 (samples, taxels).
    counts = np.round(stack([2], 4, 25)[:, :, 0] * 1000.0).astype("<i2")
    variable(f, "counts", counts, "int16")
    variable(f, "fs", np.array([[500.0]]), "double")


def complex_file(f):
    # MATLAB's complex double: a compound of `real` and `imag`.
    z = np.ascontiguousarray(stack([0], 4, 10)[:, :, 0].T)
    c = np.empty(z.shape, dtype=[("real", "<f8"), ("imag", "<f8")])
    c["real"], c["imag"] = z, -z
    d = f.create_dataset("data", data=c)
    d.attrs.create("MATLAB_class", np.bytes_("double"))
    d.attrs.create("MATLAB_complex", np.uint8(1))


if __name__ == "__main__":
    mat73(HERE / "mat73_stack.mat", stack_file)
    mat73(HERE / "mat73_int16.mat", int16_file)
    mat73(HERE / "mat73_complex.mat", complex_file)
    print("wrote", ", ".join(p.name for p in sorted(HERE.glob("mat73_*.mat"))))
