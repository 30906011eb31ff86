"""The standard 3DGS Gaussian PLY (the INRIA layout), read and written without torch.

One ``vertex`` element with float properties (docs/design.md section 3 conventions)::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1}
    opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

Stored values are raw: log-scales, the opacity logit, an unnormalised quaternion (rot_0 = w).
``f_rest`` is channel-major as the INRIA code writes it: property ``f_rest_{c (K-1) + k - 1}`` holds
SH coefficient k >= 1 of channel c. :func:`read_gaussian_ply` returns an activated
:class:`~nehad.runtime.gaussians.GaussianCloud`; :func:`write_gaussian_ply` is its inverse and
writes atomically (docs/design.md section 10).

The reader accepts binary (little or big endian) and ascii files, properties in any order and of
any numeric type, and ignores extra properties (``nx ny nz``, ...) and other elements.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from .gaussians import GaussianCloud
from .errors import InputProblem


class PlyError(InputProblem):
    """A PLY file cannot be read as (or written from) 3DGS Gaussians; the message names the file."""


_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "ascii"}
_BASE = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"]
_TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
_VALID_REST = {3 * ((d + 1) ** 2 - 1): d for d in range(4)}  # f_rest count -> SH degree
_MAX_HEADER_LINES = 100_000


class _Element:
    def __init__(self, name: str, count: int):
        self.name = name
        self.count = count
        self.props: list[tuple[str, str]] = []  # (name, numpy type code); "list" for lists

    @property
    def has_list(self) -> bool:
        return any(t == "list" for _, t in self.props)


def _parse_header(f, source: str):
    magic = f.readline(16)
    if magic.rstrip(b"\r\n") != b"ply":
        raise PlyError(f"{source}: not a PLY file (it does not start with 'ply')")
    fmt = None
    elements: list[_Element] = []
    for _ in range(_MAX_HEADER_LINES):
        raw = f.readline(4096)
        if not raw:
            raise PlyError(f"{source}: PLY header has no end_header line")
        if not raw.endswith(b"\n"):
            raise PlyError(f"{source}: PLY header line too long or unterminated")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise PlyError(f"{source}: PLY header holds non-ASCII bytes") from None
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        if key == "end_header":
            break
        if key == "format":
            if len(words) < 2 or words[1] not in _FORMATS:
                raise PlyError(f"{source}: unknown PLY format {line!r}")
            fmt = _FORMATS[words[1]]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PlyError(f"{source}: malformed element line {line!r}")
            elements.append(_Element(words[1], int(words[2])))
        elif key == "property":
            if not elements:
                raise PlyError(f"{source}: property before any element: {line!r}")
            if len(words) >= 2 and words[1] == "list":
                if len(words) != 5:
                    raise PlyError(f"{source}: malformed property line {line!r}")
                elements[-1].props.append((words[4], "list"))
                continue
            if len(words) != 3 or words[1] not in _TYPES:
                raise PlyError(f"{source}: unknown property type in {line!r}")
            elements[-1].props.append((words[2], _TYPES[words[1]]))
        else:
            raise PlyError(f"{source}: unexpected PLY header line {line!r}")
    else:
        raise PlyError(f"{source}: PLY header has no end_header line")
    if fmt is None:
        raise PlyError(f"{source}: PLY header has no format line")
    return fmt, elements, f.tell()


def _rest_names(names: list[str], source: str) -> list[str]:
    idx = sorted(int(m.group(1)) for n in names if (m := re.fullmatch(r"f_rest_(\d+)", n)))
    count = len(idx)
    if count not in _VALID_REST:
        raise PlyError(f"{source}: {count} f_rest properties; expected 0, 9, 24 or 45 "
                       f"(3*((d+1)^2-1) for SH degree d = 0..3)")
    if idx != list(range(count)):
        missing = sorted(set(range(count)) - set(idx))
        raise PlyError(f"{source}: f_rest properties are not numbered 0..{count - 1} "
                       f"(missing {', '.join(f'f_rest_{i}' for i in missing)})")
    return [f"f_rest_{i}" for i in range(count)]


def _read_binary(path: Path, vertex: _Element, offset: int, order: str, source: str) -> np.ndarray:
    """The vertex table as an (N, P) array, columns in header order.

    When every property has one type (the INRIA files) this is a read-only memory map of the
    file: nothing is copied until the caller gathers the columns it needs.
    """
    n = vertex.count
    dtype = np.dtype([(p, order + t) for p, t in vertex.props])
    need = n * dtype.itemsize
    have = os.path.getsize(path) - offset
    if have < need:
        raise PlyError(f"{source}: truncated: the header declares {n} vertices ({need} bytes) "
                       f"but only {max(have, 0)} bytes follow it")
    types = {t for _, t in vertex.props}
    if len(types) == 1:
        return np.memmap(path, dtype=order + types.pop(), mode="r", offset=offset,
                         shape=(n, len(vertex.props)))
    rec = np.fromfile(path, dtype=dtype, count=n, offset=offset)
    table = np.empty((n, len(vertex.props)), dtype=np.float64)
    for j, (p, _) in enumerate(vertex.props):
        table[:, j] = rec[p]
    return table


def _read_ascii(path: Path, elements: list[_Element], vi: int, offset: int, source: str) -> np.ndarray:
    vertex = elements[vi]
    with open(path, "rb") as f:
        f.seek(offset)
        lines = f.read().splitlines()
    skip = sum(e.count for e in elements[:vi])
    rows = lines[skip:skip + vertex.count]
    if len(rows) < vertex.count:
        raise PlyError(f"{source}: truncated: the header declares {vertex.count} vertices but only "
                       f"{len(rows)} vertex lines follow it")
    p = len(vertex.props)
    try:
        vals = np.array(b" ".join(rows).split(), dtype=np.float64)
    except ValueError:
        raise PlyError(f"{source}: non-numeric value in the vertex data") from None
    if vals.size != vertex.count * p:
        raise PlyError(f"{source}: vertex data holds {vals.size} values; the header declares "
                       f"{vertex.count} vertices x {p} properties")
    return vals.reshape(vertex.count, p)


def _columns(table: np.ndarray, idx: list[int]) -> np.ndarray:
    """table[:, idx] as a view when the columns are consecutive, else gathered."""
    if idx == list(range(idx[0], idx[0] + len(idx))):
        return table[:, idx[0]:idx[0] + len(idx)]
    return table[:, idx]


def _check_finite(table: np.ndarray, names: list[str], wanted: list[str], source: str) -> None:
    idx = [names.index(w) for w in wanted]
    # Fast path: a column whose sum is finite holds no NaN/inf. An overflowing sum only sends
    # us to the exact per-column count below.
    with np.errstate(over="ignore", invalid="ignore"):
        sums = table.sum(axis=0)
    if np.isfinite(sums[idx]).all():
        return
    bad = [(w, int(table.shape[0] - np.isfinite(table[:, i]).sum())) for w, i in zip(wanted, idx)]
    what = ", ".join(f"{w} ({b})" for w, b in bad if b)
    if what:
        raise PlyError(f"{source}: NaN or infinite values in {what}")


def read_gaussian_ply(path) -> GaussianCloud:
    """Read a 3DGS PLY into an activated :class:`GaussianCloud` (docs/design.md sections 3 and 7).

    scales = exp(scale_*), opacities = sigmoid(opacity), quats = rot_* normalised (w, x, y, z),
    sh[:, 0, c] = f_dc_c, sh[:, k, c] = f_rest_{c (K-1) + k - 1}. Raises :class:`PlyError`.
    """
    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise PlyError(f"{source}: no such PLY file")
    with open(path, "rb") as f:
        fmt, elements, offset = _parse_header(f, source)
    vi = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if vi is None:
        raise PlyError(f"{source}: no 'vertex' element in the PLY header")
    vertex = elements[vi]
    names = [p for p, _ in vertex.props]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise PlyError(f"{source}: duplicate vertex properties: {', '.join(dup)}")
    rest = _rest_names(names, source)
    wanted = _BASE + rest + _TAIL
    missing = [w for w in wanted if w not in names]
    if missing:
        raise PlyError(f"{source}: missing vertex properties: {' '.join(missing)} "
                       f"(not a 3DGS Gaussian PLY?)")
    lists = [p for p, t in vertex.props if t == "list"]
    if lists:
        raise PlyError(f"{source}: list properties in the vertex element are not supported: "
                       f"{' '.join(lists)}")
    n = vertex.count
    if n == 0:
        raise PlyError(f"{source}: the PLY holds no Gaussians (vertex count 0)")

    if fmt == "ascii":
        table = _read_ascii(path, elements, vi, offset, source)
    else:
        for e in elements[:vi]:
            if e.has_list:
                raise PlyError(f"{source}: cannot skip element {e.name!r} with list properties "
                               f"before the vertex element")
            offset += e.count * np.dtype([(p, t) for p, t in e.props]).itemsize
        table = _read_binary(path, vertex, offset, fmt, source)
    try:
        _check_finite(table, names, wanted, source)
        col = {w: names.index(w) for w in wanted}

        def group(ws):
            return _columns(table, [col[w] for w in ws])

        with np.errstate(over="ignore"):
            narrowing = table.dtype == np.float64  # values may not fit float32
            means = group(["x", "y", "z"]).astype(np.float32)
            if narrowing and not np.isfinite(means).all():
                raise PlyError(f"{source}: x/y/z: values beyond the float32 range")
            r = len(rest)
            k = r // 3 + 1
            sh = np.empty((n, k, 3), dtype=np.float32)
            sh[:, 0, :] = group(["f_dc_0", "f_dc_1", "f_dc_2"])
            if r:
                sh[:, 1:, :] = group(rest).reshape(n, 3, k - 1).transpose(0, 2, 1)
            if narrowing and not np.isfinite(sh).all():
                raise PlyError(f"{source}: f_dc/f_rest: values beyond the float32 range")
            logit = group(["opacity"])[:, 0].astype(np.float64)
            opac = (0.5 * (1.0 + np.tanh(0.5 * logit))).astype(np.float32)  # sigmoid, no overflow
            scales = np.exp(group(["scale_0", "scale_1", "scale_2"]).astype(np.float64)).astype(np.float32)
        if not np.isfinite(scales).all():
            cnt = int((~np.isfinite(scales)).any(axis=1).sum())
            raise PlyError(f"{source}: scale_0..scale_2: {cnt} log-scales are too large "
                           f"(exp overflows float32)")
        q = group(["rot_0", "rot_1", "rot_2", "rot_3"]).astype(np.float64)
    finally:
        table = None  # drop the memory map before returning
    norm = np.sqrt(np.einsum("ij,ij->i", q, q))
    zero = norm == 0
    if zero.any():
        raise PlyError(f"{source}: rot_0..rot_3: {int(zero.sum())} Gaussians have a zero-norm quaternion")
    quats = (q / norm[:, None]).astype(np.float32)
    return GaussianCloud(means=means, scales=scales, quats=quats, opacities=opac, sh=sh)


def ply_property_names(sh_degree: int) -> list[str]:
    """The INRIA property order for SH degree `sh_degree` (0..3)."""
    if sh_degree not in range(4):
        raise PlyError(f"sh degree {sh_degree}: expected 0..3")
    r = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(r)] + _TAIL)


def write_gaussian_ply(path, cloud: GaussianCloud) -> Path:
    """Write `cloud` as a binary little-endian 3DGS PLY, atomically (docs/design.md sections 3, 10).

    Inverse of :func:`read_gaussian_ply`: log-scales, opacity logits (opacities clipped to
    [1e-15, 1 - 1e-15] so that 0 and 1 stay finite), quaternions as given, normals 0.
    Refuses non-finite values, negative scales and zero-norm quaternions with :class:`PlyError`.
    """
    from .images import atomic_path

    path = Path(path)
    source = str(path)
    n = len(cloud)
    try:
        deg = cloud.sh_degree
    except ValueError as e:
        raise PlyError(f"{source}: {e}") from None
    if deg > 3:
        raise PlyError(f"{source}: SH degree {deg} > 3 does not fit the 3DGS PLY layout")
    for name in ("means", "scales", "quats", "opacities", "sh"):
        arr = getattr(cloud, name)
        bad = int((~np.isfinite(arr)).sum())
        if bad:
            raise PlyError(f"{source}: cloud.{name} holds {bad} NaN or infinite values")
    if (cloud.scales < 0).any():
        raise PlyError(f"{source}: cloud.scales holds {int((cloud.scales < 0).sum())} negative values")
    if ((cloud.opacities < 0) | (cloud.opacities > 1)).any():
        raise PlyError(f"{source}: cloud.opacities holds values outside [0, 1]")
    if (np.abs(cloud.quats).sum(axis=1) == 0).any():
        raise PlyError(f"{source}: cloud.quats holds zero-norm quaternions")

    names = ply_property_names(deg)
    k = (deg + 1) ** 2
    out = np.zeros((n, len(names)), dtype="<f4")
    out[:, 0:3] = cloud.means
    out[:, 6:9] = cloud.sh[:, 0, :]
    r = 3 * (k - 1)
    if r:
        out[:, 9:9 + r] = cloud.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, r)
    o = 9 + r
    p = np.clip(cloud.opacities.astype(np.float64), 1e-15, 1 - 1e-15)
    out[:, o] = np.log(p) - np.log1p(-p)
    out[:, o + 1:o + 4] = np.log(np.maximum(cloud.scales.astype(np.float64), 1e-30))
    out[:, o + 4:o + 8] = cloud.quats
    header = ["ply", "format binary_little_endian 1.0", "comment written by nehad",
              f"element vertex {n}"] + [f"property float {nm}" for nm in names] + ["end_header"]
    with atomic_path(path, PlyError) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            out.tofile(f)
    return path
