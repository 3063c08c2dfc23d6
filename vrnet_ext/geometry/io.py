"""Point clouds in and out: ``read_points(path) -> (N, 3) float64``, ``write_ply(path, points)``, and
``as_points(cloud)`` for any in-memory cloud (array, tensor, an object with ``.points``) or path.

Formats (by extension): PLY (``ascii``, ``binary_little_endian``, ``binary_big_endian``; the x, y, z
properties of the ``vertex`` element, whatever else it holds), PCD (``DATA ascii`` and ``binary``),
NPY (an (N, >=3) array), XYZ / TXT / PTS / CSV (whitespace- or comma-separated rows, first three
columns, ``#`` comments), KITTI ``.bin`` (float32 rows of x, y, z, reflectance). Every problem - a
missing or truncated file, a header that does not parse, no x/y/z, NaN/Inf coordinates, fewer than
3 points - raises ``PointCloudError`` (a ``ValueError``) naming the file and what was expected.
"""
from __future__ import annotations

import io
import os
import re
import warnings
from pathlib import Path

import numpy as np

from vrnet_ext.geometry.atomic import atomic_output
from vrnet_ext.geometry.transforms import chain

MIN_POINTS = 3

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
              ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


class PointCloudError(ValueError):
    """A point-cloud file that cannot be read; the message names the file."""


def _fail(path: Path, message: str) -> PointCloudError:
    return PointCloudError(f"{path}: {message}")


def _read_header(path: Path, data: bytes, terminator: str, max_bytes: int = 1 << 16) -> tuple[list[str], int]:
    """Header lines up to and including the first line whose first word is ``terminator`` (so a
    comment that mentions it does not end the header), and the offset of the body."""
    offset = 0
    lines = []
    while offset < min(len(data), max_bytes):
        end = data.find(b"\n", offset)
        end = len(data) if end < 0 else end + 1
        try:
            line = data[offset:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise _fail(path, "the header is not ASCII text") from None
        offset = end
        if line:
            lines.append(line)
            if line.split()[0] == terminator:
                return lines, offset
    raise _fail(path, f"no {terminator!r} line in the first {max_bytes} bytes: not a valid header")


def _count(path: Path, text: str, what: str) -> int:
    """A non-negative element / point count from a header."""
    try:
        value = int(text)
    except ValueError:
        raise _fail(path, f"the {what} count {text!r} is not an integer") from None
    if value < 0:
        raise _fail(path, f"the {what} count is negative ({value})")
    return value


def _parse_ply_vertex(path: Path, header: list[str]) -> tuple[str, int, list[tuple[str, str]], int]:
    """(format, vertex count, vertex properties [(name, numpy type)], bytes of elements before vertex)."""
    if header[0] != "ply":
        raise _fail(path, "a PLY file must start with the line 'ply'")
    fmt, elements, current = None, [], None
    for number, line in enumerate(header[1:], start=2):
        words = line.split()
        if words[0] in ("comment", "obj_info", "end_header"):
            continue
        if words[0] == "format" and len(words) == 3:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            current = (words[1], _count(path, words[2], f"element {words[1]!r}"), [])
            elements.append(current)
        elif words[0] == "property" and current is not None:
            if len(words) < 3:
                raise _fail(path, f"bad property line {line!r}")
            if words[1] == "list":
                current[2].append((words[-1], "list"))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                current[2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise _fail(path, f"unknown PLY property type in {line!r}")
        else:  # a misspelt keyword would shift the columns of everything after it
            raise _fail(path, f"header line {number} is not a PLY header line: {line!r} (expected format, element, "
                              f"property, comment, obj_info or end_header)")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise _fail(path, f"PLY format must be ascii, binary_little_endian or binary_big_endian, got {fmt!r}")
    skip = 0
    for name, count, props in elements:
        if name == "vertex":
            if any(t == "list" for _, t in props):
                raise _fail(path, "list properties in the vertex element are not supported")
            return fmt, count, props, skip
        if fmt != "ascii" and any(t == "list" for _, t in props):
            raise _fail(path, f"element {name!r} with list properties comes before 'vertex': not supported")
        # ascii: one line per element instance; binary: fixed-size records
        skip += count if fmt == "ascii" else count * sum(np.dtype(t).itemsize for _, t in props)
    raise _fail(path, "no 'element vertex' in the PLY header")


def _check_field_names(path: Path, names: list[str], what: str) -> None:
    """x, y and z each present exactly once among ``names``."""
    if not {"x", "y", "z"} <= set(names):
        raise _fail(path, f"{what} need x, y and z, have {names}")
    repeated = sorted({a for a in "xyz" if names.count(a) > 1})
    if repeated:
        raise _fail(path, f"{what} name {', '.join(repeated)} more than once: {names}")


def _read_ply(path: Path, data: bytes) -> np.ndarray:
    header, body = _read_header(path, data, "end_header")
    fmt, count, props, skip = _parse_ply_vertex(path, header)
    names = [name for name, _ in props]
    _check_field_names(path, names, "the vertex element's properties")
    if fmt == "ascii":
        columns = [names.index(a) for a in "xyz"]
        table = _text_rows(path, data[body:], count, skip, columns, f"vertex lines with {len(props)} numbers")
        if table.shape[0] < count:
            raise _fail(path, f"truncated: header promises {count} vertices, found {table.shape[0]} lines")
        return table
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(name, order + t) for name, t in props])
    needed = body + skip + count * dtype.itemsize
    if len(data) < needed:
        raise _fail(path, f"truncated: {count} vertices need {needed} bytes, the file has {len(data)}")
    vertices = np.frombuffer(data, dtype=dtype, count=count, offset=body + skip)
    return np.stack([vertices[a] for a in "xyz"], axis=1)


def _text_rows(path: Path, body: bytes, count: int, skip: int, columns: list[int], what: str) -> np.ndarray:
    """``count`` rows (after ``skip`` lines) of whitespace-separated numbers -> (rows, len(columns))
    float64, parsed by numpy's streaming reader: memory of the result only, not of Python strings."""
    # No allocation sized by the header alone: at most as many rows as the body has lines.
    count = min(count, max(0, body.count(b"\n") + 1 - skip))
    if count == 0:
        return np.empty((0, len(columns)))
    try:
        table = np.loadtxt(io.BytesIO(body), dtype=np.float64, skiprows=skip, max_rows=count, usecols=columns,
                           ndmin=2, encoding="latin-1")
    except (ValueError, IndexError):
        raise _fail(path, f"the data must be {what}") from None
    return table


def _read_pcd(path: Path, data: bytes) -> np.ndarray:
    header, body = _read_header(path, data, "DATA")
    fields: dict[str, list[str]] = {}
    for line in header:
        if not line.startswith("#"):
            key, *values = line.split()
            fields[key.upper()] = values
    try:
        names = fields["FIELDS"]
        sizes = [int(s) for s in fields["SIZE"]]
        types = fields["TYPE"]
        counts = [int(c) for c in fields.get("COUNT", ["1"] * len(names))]
        mode = fields["DATA"][0].lower()
        if "POINTS" in fields:
            points = _count(path, fields["POINTS"][0], "POINTS")
        else:
            points = _count(path, fields["WIDTH"][0], "WIDTH") * _count(path, fields["HEIGHT"][0], "HEIGHT")
    except (KeyError, IndexError, ValueError) as exc:
        raise _fail(path, f"PCD header misses or mangles {exc}: needs FIELDS, SIZE, TYPE, POINTS and DATA") from None
    _check_field_names(path, names, "PCD FIELDS")
    if not len(names) == len(sizes) == len(types) == len(counts):
        raise _fail(path, "PCD FIELDS, SIZE, TYPE and COUNT must have one entry per field")
    vector_axes = [a for a in "xyz" if counts[names.index(a)] != 1]
    if vector_axes:
        raise _fail(path, f"PCD COUNT of {', '.join(vector_axes)} must be 1 (one coordinate per point), got "
                          f"{[counts[names.index(a)] for a in vector_axes]}")
    if "POINTS" in fields and {"WIDTH", "HEIGHT"} <= fields.keys():
        width, height = _count(path, fields["WIDTH"][0], "WIDTH"), _count(path, fields["HEIGHT"][0], "HEIGHT")
        if width * height != points:
            raise _fail(path, f"PCD WIDTH x HEIGHT ({width} x {height}) does not match POINTS ({points})")
    if mode == "ascii":
        offsets = np.cumsum([0] + counts)
        columns = [int(offsets[names.index(a)]) for a in "xyz"]
        rows = sum(1 for line in data[body:].splitlines() if line.strip())
        if rows > points:
            raise _fail(path, f"the header promises {points} points, the data has {rows} rows")
        table = _text_rows(path, data[body:], points, 0, columns, "PCD ascii rows with one number per field value")
        if table.shape[0] < points:
            raise _fail(path, f"truncated: header promises {points} points, found {table.shape[0]} rows")
        return table
    if mode == "binary":
        try:
            dtype = np.dtype([(name, "<" + _PCD_TYPES[(t.upper(), s)], (c,) if c > 1 else ())
                              for name, s, t, c in zip(names, sizes, types, counts)])
        except KeyError:
            raise _fail(path, f"unsupported PCD TYPE/SIZE combination in {list(zip(types, sizes))}") from None
        if len(data) < body + points * dtype.itemsize:
            raise _fail(path, f"truncated: {points} points need {points * dtype.itemsize} bytes of data")
        if len(data) > body + points * dtype.itemsize:
            raise _fail(path, f"the header promises {points} points of {dtype.itemsize} bytes, the data holds "
                              f"{len(data) - body} bytes")
        table = np.frombuffer(data, dtype=dtype, count=points, offset=body)
        return np.stack([table[a] for a in "xyz"], axis=1)
    raise _fail(path, f"PCD DATA {mode!r} is not supported (ascii or binary; convert binary_compressed with "
                      "pcl_convert_pcd_ascii_binary)")


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _header_rows(path: Path, first: str, delimiter: str | None) -> int:
    """1 when the first line is a header row of names (``x y z``, ``X,Y,Z,intensity``), 0 when it is
    a row of numbers (``1.0E+00`` included); a row that mixes the two is neither: PointCloudError."""
    tokens = [t.strip() for t in first.split(delimiter)] if delimiter else first.split()
    tokens = [t for t in tokens if t]
    numeric = [_is_number(t) for t in tokens]
    if all(numeric):
        return 0
    if not any(numeric):
        return 1
    raise _fail(path, f"line 1 mixes numbers and words: {first.strip()!r} (rows must be numbers x y z ...; a "
                      f"header row, names only)")


def _read_text(path: Path) -> np.ndarray:
    delimiter = "," if path.suffix.lower() == ".csv" else None
    with path.open("rb") as f:
        first = f.readline().decode("latin-1")
    header = _header_rows(path, first.split("#")[0], delimiter)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": reported below
            table = np.loadtxt(path, comments="#", delimiter=delimiter, ndmin=2, skiprows=header)
    except ValueError as exc:
        raise _fail(path, f"rows must be numbers (x y z ...): {exc}") from None
    if table.size == 0:
        raise _fail(path, "rows must be numbers (x y z ...): no rows of numbers found")
    if table.shape[1] < 3:
        raise _fail(path, f"rows need at least 3 columns (x y z), got {table.shape[1]}")
    if table.shape == (4, 4) and np.allclose(table[3], [0, 0, 0, 1]):
        raise _fail(path, "holds a 4x4 transform, not a point cloud (a ground truth?)")
    return table[:, :3]


def _read_npy(path: Path) -> np.ndarray:
    # Memory-mapped: the header's shape is checked against the file's size before anything is read,
    # so a header claiming 10^10 rows fails at once instead of allocating them.
    try:
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as exc:  # numpy's header parser raises many types (ValueError, SyntaxError, TokenError, ...)
        raise _fail(path, f"not a readable .npy array ({type(exc).__name__}: {exc})") from None
    if not isinstance(array, np.ndarray):  # np.load opens a .npz archive whatever the name says
        array.close()
        raise _fail(path, "is a .npz archive, not a .npy array (save one array with numpy.save)")
    real = np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating)
    if array.ndim != 2 or array.shape[1] < 3 or not real:
        raise _fail(path, f"expected a real-valued (N, >=3) integer or float array, got {array.dtype} {array.shape}")
    return np.array(array[:, :3])


def _read_kitti(path: Path, data: bytes) -> np.ndarray:
    if len(data) % 16:
        raise _fail(path, f"a KITTI .bin holds float32 (x, y, z, reflectance) rows of 16 bytes; {len(data)} bytes is not a multiple")
    return np.frombuffer(data, dtype="<f4").reshape(-1, 4)[:, :3]


READERS = {".ply": "ply", ".pcd": "pcd", ".npy": "npy", ".xyz": "text", ".txt": "text", ".pts": "text",
           ".csv": "text", ".bin": "kitti"}


def read_points(path: str | os.PathLike) -> np.ndarray:
    """Reads the x, y, z coordinates of a point-cloud file.

    Returns:
        (N, 3) float64 array, N >= 3, all values finite (float64 whatever the file stores, so that
        georeferenced coordinates such as UTM northings keep their centimetres).
    """
    path = Path(path)
    kind = READERS.get(path.suffix.lower())
    if kind is None:
        raise _fail(path, f"unknown extension {path.suffix!r}; supported: {', '.join(sorted(READERS))}")
    if not path.is_file():
        raise PointCloudError(f"{path}: no such file")
    if kind == "text":
        points = _read_text(path)
    elif kind == "npy":
        points = _read_npy(path)
    else:
        data = path.read_bytes()
        points = {"ply": _read_ply, "pcd": _read_pcd, "kitti": _read_kitti}[kind](path, data)
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.shape[0] < MIN_POINTS:
        raise _fail(path, f"needs at least {MIN_POINTS} points, has {points.shape[0]}")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise _fail(path, f"{int(bad.sum())} points have NaN or Inf coordinates (first: row {int(np.argmax(bad))})")
    return points


def as_points(cloud, name: str = "cloud") -> np.ndarray:
    """Any point cloud as an (N, 3) float64 array: a numpy array or torch tensor of shape (N, 3), an
    object with a ``points`` attribute holding one (an Open3D ``PointCloud``, without importing
    Open3D), or a file path (:func:`read_points`). Raises ``ValueError`` naming ``name`` when it is
    none of these, has another shape, fewer than 3 points, or NaN/Inf coordinates."""
    if isinstance(cloud, (str, os.PathLike)):
        return read_points(cloud)
    if hasattr(cloud, "points") and not hasattr(cloud, "shape"):
        cloud = cloud.points
    if hasattr(cloud, "detach"):  # a torch tensor, on any device
        cloud = cloud.detach().cpu().numpy()
    try:
        points = np.asarray(cloud, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name} must be an (N, 3) array, tensor, point cloud or file path, "
                         f"got {type(cloud).__name__}") from error
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {points.shape}")
    if points.shape[0] < MIN_POINTS:
        raise ValueError(f"{name} needs at least {MIN_POINTS} points, has {points.shape[0]}")
    if not np.isfinite(points).all():
        raise ValueError(f"{name} has NaN or Inf coordinates")
    return np.ascontiguousarray(points)


def write_ply(path: str | os.PathLike, points: np.ndarray) -> None:
    """Writes (N, 3) points as a binary little-endian PLY with float x, y, z, or double where float
    would blur them (coordinates far from the origin compared with the cloud's extent)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    extent = float(np.max(points.max(axis=0) - points.min(axis=0))) if len(points) else 0.0
    largest = float(np.abs(points).max()) if len(points) else 0.0
    wide = float(np.spacing(np.float32(largest))) > 1e-6 * extent
    points = points.astype("<f8" if wide else "<f4")
    kind = "double" if wide else "float"
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              f"property {kind} x\nproperty {kind} y\nproperty {kind} z\nend_header\n")
    with atomic_output(path) as temporary, open(temporary, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(np.ascontiguousarray(points).tobytes())


MAX_LOG_BYTES = 1 << 24  # a 3DMatch-style log of a whole scene is well under 1 MB
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def read_transform(path: str | os.PathLike) -> np.ndarray:
    """A 4x4 rigid transform written as 16 numbers (rows; '#' comments ignored) -> (4, 4) float64."""
    path = Path(path)
    rows = _number_rows(path)
    numbers = [float(v) for row in rows for v in row]
    if len(numbers) != 16:
        hint = " (a 3DMatch log: read_ground_truth)" if _is_log(rows) else ""
        raise _fail(path, f"a 4x4 transform needs 16 numbers, found {len(numbers)}{hint}")
    return _rigid(path, np.array(numbers).reshape(4, 4))


def read_poses(path: str | os.PathLike, scans: list[str | os.PathLike]) -> np.ndarray:
    """One ground-truth pose per scan (``T_world_scan``, in the order of ``scans``) from a text
    file: one line of 12 numbers per pose (the top three rows of the 4x4, as KITTI's poses.txt), one
    line of 16, or four lines of 4 numbers each ('#' comments ignored); or a 3DMatch ``gt.log`` of
    pairs, the scans named ``cloud_bin_<i>`` as the benchmark names them, chained from the first
    scan (its frame is then the world's) -> (len(scans), 4, 4) float64."""
    path, count = Path(path), len(scans)
    rows = _number_rows(path)
    if _is_log(rows):
        return _chained_log(path, rows, scans)
    widths = {len(row) for row in rows}
    if widths == {12} and len(rows) == count:
        matrices = [np.vstack([np.array(row, dtype=np.float64).reshape(3, 4), [0, 0, 0, 1]]) for row in rows]
    elif widths == {16} and len(rows) == count:
        matrices = [np.array(row, dtype=np.float64).reshape(4, 4) for row in rows]
    elif widths == {4} and len(rows) == 4 * count:
        matrices = [np.array(rows[4 * k:4 * k + 4], dtype=np.float64) for k in range(count)]
    else:
        raise _fail(path, f"expected {count} poses (one line of 12 or 16 numbers each, or 4 lines of 4), found "
                          f"{len(rows)} lines of {sorted(widths)} numbers")
    return np.stack([_rigid(path, T) for T in matrices])


def _chained_log(path: Path, rows: list[list[str]], scans: list[str | os.PathLike]) -> np.ndarray:
    """The poses of ``scans`` (named cloud_bin_<i>) chained through the pairs of a 3DMatch log."""
    found = [_FRAGMENT.search(Path(scan).stem) for scan in scans]
    if not all(found):
        unnamed = [str(scan) for scan, match in zip(scans, found) if not match]
        raise _fail(path, f"a 3DMatch log names fragments by index: name the scans cloud_bin_<index> ({unnamed[0]} "
                          f"is not)")
    index = {int(match.group(1)): k for k, match in enumerate(found)}
    links = []
    for k in range(0, len(rows), 5):
        i, j = int(float(rows[k][0])), int(float(rows[k][1]))
        if i in index and j in index:  # fragment j into fragment i's frame
            links.append((index[i], index[j], _rigid(path, _log_pair(path, rows[k:k + 5], None))))
    poses, reached = chain(len(scans), links)
    if not reached.all():
        missing = [str(scan) for scan, linked in zip(scans, reached) if not linked]
        raise _fail(path, f"no chain of the log's pairs links {', '.join(missing)} to {scans[0]}")
    return poses


_FRAGMENT = re.compile(r"cloud_bin_(\d+)$")  # how the 3DMatch benchmark names its fragments


def read_ground_truth(path: str | os.PathLike, source: str | os.PathLike | None = None,
                      target: str | os.PathLike | None = None, fragments: tuple[int, int] | None = None) -> np.ndarray:
    """The ground truth ``T_target_source`` (4, 4) of a pair from ``path``: a 4x4 transform
    (:func:`read_transform`), or one pair of a 3DMatch ``gt.log`` (blocks of a line ``i j n`` and the
    4x4 that maps fragment j into the frame of fragment i). For a log, ``fragments=(source index,
    target index)`` picks the pair, else the indices of the ``source`` and ``target`` file names
    (``cloud_bin_<i>.ply``, as the benchmark names them), else the log must hold one pair. The
    block ``target source`` is used as it is, ``source target`` inverted."""
    path = Path(path)
    rows = _number_rows(path)
    if not _is_log(rows):
        if fragments is not None:
            raise _fail(path, f"fragments {fragments} were given, but this is a 4x4 transform, not a 3DMatch log")
        return read_transform(path)
    if fragments is None and source is not None and target is not None:
        found = [_FRAGMENT.search(Path(name).stem) for name in (source, target)]
        fragments = (int(found[0].group(1)), int(found[1].group(1))) if all(found) else None
    return _rigid(path, _log_pair(path, rows, fragments))


def _number_rows(path: Path) -> list[list[str]]:
    """The numbers of each line of a small text file (blank and '#' lines dropped)."""
    if not path.is_file():
        raise PointCloudError(f"{path}: no such file")
    if path.stat().st_size > MAX_LOG_BYTES:
        raise _fail(path, f"too large for a transform or a 3DMatch log ({path.stat().st_size} bytes)")
    try:
        text = path.read_text(encoding="ascii")
    except UnicodeDecodeError:
        raise _fail(path, "a transform must be a text file of numbers (this one is not ASCII text)") from None
    lines = [line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    return [re.findall(_NUMBER, line) for line in lines]


def _is_log(rows: list[list[str]]) -> bool:
    """Whether the lines are a 3DMatch log: 5 per pair, the first of each holding ``i j n``."""
    return bool(rows) and len(rows) % 5 == 0 and all(len(rows[k]) == 3 for k in range(0, len(rows), 5))


def _log_pair(path: Path, rows: list[list[str]], fragments: tuple[int, int] | None) -> np.ndarray:
    """The 4x4 of a 3DMatch log (``rows``: its lines as numbers) for ``fragments`` (source, target)."""
    blocks = {}
    for k in range(0, len(rows), 5):
        matrix = rows[k + 1:k + 5]
        if any(len(row) != 4 for row in matrix):
            raise _fail(path, f"3DMatch log entry {' '.join(rows[k])}: the 4 lines after it need 4 numbers each")
        blocks[(int(float(rows[k][0])), int(float(rows[k][1])))] = np.array(matrix, dtype=np.float64)
    if fragments is None:
        if len(blocks) != 1:
            raise _fail(path, f"a 3DMatch log of {len(blocks)} pairs: give the fragments (source and target "
                              f"indices), or name the clouds cloud_bin_<index>")
        return next(iter(blocks.values()))
    source, target = fragments
    if (target, source) in blocks:
        return blocks[(target, source)]
    if (source, target) in blocks:
        return np.linalg.inv(blocks[(source, target)])
    raise _fail(path, f"the 3DMatch log has no entry for fragments {source} and {target}")


def _rigid(path: Path, T: np.ndarray) -> np.ndarray:
    """``T`` if it is a rigid transform, else PointCloudError."""
    # published ground truth is only ~1e-4 orthonormal (3DMatch's gt.log: up to 1.3e-4)
    rotation = T[:3, :3]
    if (not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3)
            or np.linalg.det(rotation) <= 0):
        raise _fail(path, "not a rigid transform (last row 0 0 0 1, orthonormal rotation block with det +1)")
    return T
