"""Independent float64 references for `.data` strand files and arc-length resampling."""

import struct

import numpy as np


def encode_hair_data(strands) -> bytes:
    """The USC-HairSalon layout byte by byte: int32 count, then per strand int32 n + n*3 float32."""
    out = bytearray(struct.pack("<i", len(strands)))
    for s in strands:
        s = np.asarray(s, dtype=np.float64)
        out += struct.pack("<i", len(s))
        for x, y, z in s:
            out += struct.pack("<fff", x, y, z)
    return bytes(out)


def resample_polyline(points, n):
    """One polyline (K, 3) -> (n, 3) points at equal arc-length steps, one by one."""
    p = np.asarray(points, dtype=np.float64)
    seg = [float(np.linalg.norm(p[i + 1] - p[i])) for i in range(len(p) - 1)]
    total = sum(seg)
    out = []
    for j in range(n):
        target = total * j / (n - 1)
        acc = 0.0
        for i, L in enumerate(seg):
            if acc + L >= target or i == len(seg) - 1:
                w = 0.0 if L == 0 else min(max((target - acc) / L, 0.0), 1.0)
                out.append(p[i] + w * (p[i + 1] - p[i]))
                break
            acc += L
    return np.array(out)
