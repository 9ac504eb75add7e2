#!/usr/bin/env python3
"""Writes the seed corpus of every fuzz target into fuzz/corpus/<target>/seed-*.

Seeds are small valid inputs (and a few near misses) built from the repository's
graphs and the formats the readers document; libFuzzer mutates from there.
Standard library only, so it runs on a fresh machine. Run from anywhere."""
import io, os, struct, zipfile, zlib, glob, random

root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
corpus = os.path.join(root, "fuzz", "corpus")


def put(target, name, data):
    d = os.path.join(corpus, target)
    os.makedirs(d, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    with open(os.path.join(d, "seed-" + name), "wb") as f:
        f.write(data)


def npy(descr, shape, payload, fortran=False):
    shape_s = "(" + "".join(f"{d}, " for d in shape)[:-1] + ("," if len(shape) == 1 else "") + ")"
    h = "{'descr': %s, 'fortran_order': %s, 'shape': %s, }" % (descr, "True" if fortran else "False", shape_s)
    while (10 + len(h) + 1) % 64:
        h += " "
    h += "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(h)) + h.encode() + payload


def f8(vals):
    return b"".join(struct.pack("<d", v) for v in vals)


def npz(members, deflate):
    b = io.BytesIO()
    with zipfile.ZipFile(b, "w", zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED) as z:
        for name, data in members:
            z.writestr(name, data)
    return b.getvalue()


def mat(vars_):
    def el(ty, payload):
        b = struct.pack("<II", ty, len(payload)) + payload
        return b + b"\0" * (-len(b) % 8)
    out = b"MATLAB 5.0 MAT-file, palpate fuzz seed".ljust(116, b" ") + b"\0" * 8 + struct.pack("<H", 0x0100) + b"IM"
    for name, dims, data in vars_:
        m = el(6, struct.pack("<II", 6, 0)) + el(5, b"".join(struct.pack("<i", d) for d in dims))
        m += el(1, name.encode()) + el(9, f8(data))
        out += el(14, m)
    return out


def frame(fmt, seq, ts, vals):
    n = len(vals)
    body = bytes([0xAA, 0x55, 1, fmt]) + struct.pack("<HIQ", n, seq, ts)
    body += b"".join(struct.pack("<H", int(v)) if fmt == 1 else struct.pack("<f", v) for v in vals)
    return body + struct.pack("<I", zlib.crc32(body))


rng = random.Random(20)
sig = [[1.75 + 0.01 * x + 0.001 * k for x in range(16)] for k in range(12)]  # [sample][taxel]

# graph_load: every graph of the repository.
for p in sorted(glob.glob(os.path.join(root, "graphs", "**", "*.toml"), recursive=True)):
    put("graph_load", os.path.relpath(p, root).replace("/", "_"), open(p, "rb").read())

# signal_csv
hdr = "time_ms," + ",".join(f"taxel_{i}" for i in range(16))
rows = "\n".join(f"{k}," + ",".join(repr(v) for v in r) for k, r in enumerate(sig))
put("signal_csv", "plain.csv", hdr + "\n" + rows + "\n")
put("signal_csv", "trials.csv", "trial,angle_deg," + hdr + "\n" + "\n".join(
    f"t{k % 2},{30 * (k % 2)}," + f"{k // 2}," + ",".join(repr(v) for v in r) for k, r in enumerate(sig)) + "\n")
put("signal_csv", "cut.csv", hdr + "\n" + rows)

# signal_npy, spike_npy
flat = [v for r in sig for v in r]
put("signal_npy", "2d.npy", npy("'<f8'", (12, 16), f8(flat)))
put("signal_npy", "3d-f4.npy", npy("'<f4'", (2, 6, 16), b"".join(struct.pack("<f", v) for v in flat)))
put("signal_npy", "fortran.npy", npy("'<f8'", (12, 16), f8(flat), fortran=True))
put("signal_npy", "u2.npy", npy("'>u2'", (12, 16), b"".join(struct.pack(">H", int(v * 1000)) for v in flat)))
events = [(k % 4, (k // 4) % 4, 100.0 * k, k % 2) for k in range(10)]
put("spike_npy", "plain.npy", npy("'<f8'", (10, 4), f8([c for e in events for c in e])))
rec = "[('x', '<u2'), ('y', '<u2'), ('t', '<i8'), ('p', '|i1')]"
put("spike_npy", "record.npy", npy(rec, (10,), b"".join(struct.pack("<HHqb", *map(int, e)) for e in events)))

# signal_npz
members = [("data.npy", npy("'<f8'", (12, 16), f8(flat))), ("sample_rate_hz.npy", npy("'<f8'", (), f8([1000.0]))),
           ("angle_deg.npy", npy("'<f8'", (1,), f8([45.0])))]
put("signal_npz", "stored.npz", npz(members, False))
put("signal_npz", "deflated.npz", npz(members, True))

# signal_mat: data(sample, taxel) column-major, plus fs.
colmajor = [sig[k][x] for x in range(16) for k in range(12)]
put("signal_mat", "2d.mat", mat([("fs", [1, 1], [1000.0]), ("data", [12, 16], colmajor)]))
put("signal_mat", "3d.mat", mat([("data", [6, 16, 2], colmajor), ("angle_deg", [1, 2], [10.0, 20.0])]))
# MATLAB v7.3 (HDF5) files as libhdf5 writes them (stages/tests/data/make_mat73.py),
# and v5 files as SciPy writes them (make_mat5.py: int32, logical, char, cell,
# struct, sparse, complex; compressed and not).
mats = ["mat73_*.mat", "mat5_*.mat"]
for path in sorted(p for m in mats for p in glob.glob(os.path.join(root, "stages", "tests", "data", m))):
    with open(path, "rb") as f:
        put("signal_mat", os.path.basename(path), f.read())

# signal_daq, daq_decoder (the decoder's first byte is a control byte)
u16s = b"".join(frame(1, k, 1000 * k, [1000 + x for x in range(16)]) for k in range(8))
f32s = b"".join(frame(2, 0xFFFFFFFE + k & 0xFFFFFFFF, 1000 * k, sig[k]) for k in range(8))
gap = b"".join(frame(2, s, 1000 * s, sig[s % 12]) for s in [0, 1, 2, 5, 6])
put("signal_daq", "u16.daq", u16s)
put("signal_daq", "f32-wrap.daq", f32s)
put("signal_daq", "gap.daq", gap)
put("signal_daq", "noise.daq", b"\x00\xAA\x55\x01" + u16s[:50] + bytes(rng.randrange(256) for _ in range(40)) + u16s)
for ctl, name, data in [(0x07, "u16", u16s), (0x41, "f32-fixed16", f32s), (0x80 | 0x03, "gap-fill", gap),
                        (0x20, "noise", b"\xAA" + u16s[3:] + b"\xAA\x55")]:
    put("daq_decoder", name, bytes([ctl]) + data)

# spike_csv
put("spike_csv", "plain.csv", "x,y,t,p\n" + "\n".join(",".join(str(c) for c in e) for e in events) + "\n")
put("spike_csv", "trials.csv", "trial,angle_deg,duration_ms,x,y,t\n" + "\n".join(
    f"r{k % 3},{15 * (k % 3)},5000,{e[0]},{e[1]},{e[2]}" for k, e in enumerate(events)) + "\n")

# label_sidecar (first byte: even = TOML, odd = CSV)
put("label_sidecar", "toml", b"\x00" + b'[trials.rec01]\nangle_deg = 45.0\nstimulus = "edge"\ngroup = 0\nduration_ms = 9500.0\n\n[trials."a b"]\nstimulus = "ridge"\n')
put("label_sidecar", "csv", b"\x01" + b"trial,angle_deg,stimulus,group,duration_ms\nrec01,45,edge,0,9500\nrec02,,unknown,1,\n")

# spike_bin: arbitrary-derived (window, hop, duration, events); raw bytes work.
put("spike_bin", "paper", struct.pack("<ddd", 100.0, 10.0, 1000.0) + b"".join(
    bytes([k % 16]) + struct.pack("<d", 37.5 * k) for k in range(20)))
put("spike_bin", "short-window", struct.pack("<ddd", 5.0, 7.0, 300.0) + bytes(64))
print("seeds written to", corpus)
