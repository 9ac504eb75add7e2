"""Writes the MATLAB v5 test files beside this script with SciPy's `savemat`
(run once; the files are committed, so the tests need no Python):

    pip install scipy numpy && python stages/tests/data/make_mat5.py

Tested by the unit tests of stages/src/io/mat5.rs and stages/tests/io_files.rs.
`mat5_int32.mat` and `mat5_int32_z.mat` (the same variables, compressed)
hold what a MATLAB user saves beside int32 ADC counts: `fs = int32(1000)`,
`data` a 2x16 int32 array (values 0..31, row-major: `data[i, j] = 16 i + j`,
negated for odd values to cover the sign), a logical row, and variables the
reader passes over: a char array, a cell array, a struct. `mat5_sparse.mat`
and `mat5_complex.mat` hold one variable each that the reader refuses.
The `matfile` crate the reader replaced could read no int32 variable.
"""

import pathlib

import numpy as np
import scipy.io as sio
import scipy.sparse as sp

HERE = pathlib.Path(__file__).resolve().parent

data = np.arange(32, dtype="int32").reshape(2, 16)
data[data % 2 == 1] *= -1
cell = np.empty((1, 2), dtype=object)
cell[0, 0] = np.array([1.0, 2.0])
cell[0, 1] = "text"
variables = dict(
    name="trial one",
    fs=np.int32(1000),
    cells=cell,
    meta=dict(angle=30.0, who="bench"),
    data=data,
    touching=np.array([[True, False, True]]),
)
for path, compress in [("mat5_int32.mat", False), ("mat5_int32_z.mat", True)]:
    sio.savemat(HERE / path, variables, do_compression=compress, oned_as="row")
sio.savemat(HERE / "mat5_sparse.mat", dict(fs=1000.0, s=sp.csc_matrix(np.eye(3))))
sio.savemat(HERE / "mat5_complex.mat", dict(fs=1000.0, z=np.array([[1 + 2j, 3.0]])))
