"""VTK XML unstructured grids (``.vtu``) written and read with numpy alone.

The storm's ParaView series (:class:`hailstorm.runtime.output.files.ParaviewSeries`)
is part of the core install, which has no meshio: this module writes the subset
of the format the series needs, in the layout meshio and VTK write by default
(little- or big-endian as the machine, ``UInt32`` headers, each array zlib-compressed
in blocks of 32 KiB and base64-encoded inline), and reads back what it wrote. The
tests read its files with meshio and write meshio's files for it to read.

Cell types: ``"vertex"`` (VTK 1) and ``"triangle"`` (VTK 5), the two the series writes.
"""

from __future__ import annotations

import base64
import os
import sys
import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import numpy as np

__all__ = ["VTK_CELL_TYPES", "read_vtu", "read_vtu_cells", "write_vtu"]

#: cell name -> (VTK cell type, nodes per cell)
VTK_CELL_TYPES: dict[str, tuple[int, int]] = {"vertex": (1, 1), "triangle": (5, 3)}
#: numpy dtype -> the format's type name, both ways
_VTU_TYPES = {np.dtype(np.float64): "Float64", np.dtype(np.float32): "Float32", np.dtype(np.int64): "Int64",
              np.dtype(np.int32): "Int32", np.dtype(np.uint8): "UInt8", np.dtype(np.uint32): "UInt32",
              np.dtype(np.uint64): "UInt64"}
_NUMPY_TYPES = {v: k for k, v in _VTU_TYPES.items()}
#: VTK's zlib block size (vtkZLibDataCompressor's default)
_BLOCK = 32768
_BYTE_ORDER = "LittleEndian" if sys.byteorder == "little" else "BigEndian"


def _encode(data: np.ndarray) -> str:
    """One array as VTK's compressed inline binary: base64(header) + base64(blocks)."""
    raw = np.ascontiguousarray(data).tobytes()
    blocks = [zlib.compress(raw[i:i + _BLOCK]) for i in range(0, len(raw), _BLOCK)] or [zlib.compress(b"")]
    last = len(raw) - (len(blocks) - 1) * _BLOCK
    header = np.array([len(blocks), _BLOCK, last, *map(len, blocks)], dtype=np.uint32)
    return base64.b64encode(header.tobytes()).decode() + base64.b64encode(b"".join(blocks)).decode()


def _array(parent: ET.Element, name: str, data: np.ndarray) -> None:
    data = np.asarray(data)
    if data.dtype not in _VTU_TYPES:
        raise TypeError(f"vtu: no VTK type for array {name!r} of dtype {data.dtype}")
    el = ET.SubElement(parent, "DataArray", type=_VTU_TYPES[data.dtype], Name=name, format="binary")
    if data.ndim == 2:
        el.set("NumberOfComponents", str(data.shape[1]))
    el.text = _encode(data)


def write_vtu(path: str | os.PathLike, points: np.ndarray, cell_type: str, cells: np.ndarray,
              point_data: dict[str, np.ndarray] | None = None) -> Path:
    """Write an unstructured grid of one cell type.

    Parameters
    ----------
    path : path
        The ``.vtu`` file (overwritten).
    points : (N, 3) array_like
        Point coordinates.
    cell_type : str
        A key of :data:`VTK_CELL_TYPES`.
    cells : (C, k) array_like of int
        Point indices of each cell (``k`` nodes per cell of the type).
    point_data : dict, optional
        Name -> ``(N,)`` or ``(N, m)`` array of a dtype of the format (float32/64,
        int32/64, uint8/32/64).

    Returns
    -------
    Path
    """
    vtk_type, k = VTK_CELL_TYPES[cell_type]
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    conn = np.asarray(cells, dtype=np.int64).reshape(-1, k)
    root = ET.Element("VTKFile", type="UnstructuredGrid", version="0.1", byte_order=_BYTE_ORDER,
                      compressor="vtkZLibDataCompressor")
    piece = ET.SubElement(ET.SubElement(root, "UnstructuredGrid"), "Piece", NumberOfPoints=str(len(pts)),
                          NumberOfCells=str(len(conn)))
    _array(ET.SubElement(piece, "Points"), "Points", pts)
    cl = ET.SubElement(piece, "Cells")
    _array(cl, "connectivity", conn.ravel())
    _array(cl, "offsets", k * np.arange(1, len(conn) + 1, dtype=np.int64))
    _array(cl, "types", np.full(len(conn), vtk_type, dtype=np.uint8))
    pd = ET.SubElement(piece, "PointData")
    for name, values in (point_data or {}).items():
        values = np.asarray(values)
        if values.shape[0] != len(pts):
            raise ValueError(f"vtu: point data {name!r} has {values.shape[0]} rows for {len(pts)} points")
        _array(pd, name, values)
    path = Path(path)
    ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)
    return path


def _decode(el: ET.Element, header_type: np.dtype, compressed: bool, order: str) -> np.ndarray:
    dtype = _NUMPY_TYPES[el.get("type", "")].newbyteorder(order)
    text = "".join((el.text or "").split())
    if el.get("format") == "ascii":
        data = np.array((el.text or "").split(), dtype=dtype.newbyteorder("="))
    elif not compressed:  # base64(header + data)
        raw = base64.b64decode(text)
        data = np.frombuffer(raw[header_type.itemsize:], dtype=dtype)
    else:  # base64(header) + base64(blocks): the header's length follows from its first item
        first = np.frombuffer(base64.b64decode(text[:_b64_len(3 * header_type.itemsize)])[:3 * header_type.itemsize],
                              dtype=header_type)
        n_blocks = int(first[0])
        hlen = _b64_len((3 + n_blocks) * header_type.itemsize)
        header = np.frombuffer(base64.b64decode(text[:hlen]), dtype=header_type)
        body = base64.b64decode(text[hlen:])
        parts, at = [], 0
        for size in header[3:3 + n_blocks]:
            parts.append(zlib.decompress(body[at:at + int(size)]))
            at += int(size)
        data = np.frombuffer(b"".join(parts), dtype=dtype)
    comps = int(el.get("NumberOfComponents", "1"))
    data = data.astype(dtype.newbyteorder("="))
    return data.reshape(-1, comps) if comps > 1 else data


def _b64_len(n: int) -> int:
    """Characters of the base64 encoding of ``n`` bytes."""
    return 4 * -(-n // 3)


def read_vtu(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read the points and point data of a ``.vtu`` file (inline ascii or binary, zlib or none).

    Parameters
    ----------
    path : path

    Returns
    -------
    points : (N, 3) ndarray
    point_data : dict
        Name -> array, ``(N,)`` or ``(N, m)``.

    Raises
    ------
    ValueError
        Not an unstructured grid this reader understands (appended data, another compressor).
    """
    root = ET.parse(path).getroot()
    if root.get("type") != "UnstructuredGrid":
        raise ValueError(f"{path}: not a VTK unstructured grid")
    compressor = root.get("compressor")
    if compressor not in (None, "vtkZLibDataCompressor"):
        raise ValueError(f"{path}: compressor {compressor} is not supported")
    header = _NUMPY_TYPES[root.get("header_type", "UInt32")]
    order = "<" if root.get("byte_order", _BYTE_ORDER) == "LittleEndian" else ">"
    piece = root.find("UnstructuredGrid/Piece")
    if piece is None or piece.find("Points/DataArray") is None:
        raise ValueError(f"{path}: no points")
    if any(el.get("format") == "appended" for el in piece.iter("DataArray")):
        raise ValueError(f"{path}: appended data is not supported")
    header = header.newbyteorder(order)
    points = _decode(piece.find("Points/DataArray"), header, compressor is not None, order)  # type: ignore[arg-type]
    data = {el.get("Name", ""): _decode(el, header, compressor is not None, order)
            for el in piece.findall("PointData/DataArray")}
    return points.reshape(-1, 3), data


def read_vtu_cells(path: str | os.PathLike, nodes: int) -> np.ndarray:
    """The cells of a ``.vtu`` file of one cell type with ``nodes`` points each, as a (C, nodes)
    int64 array of point indices (what :func:`write_vtu` wrote; the viewer reads the seat's
    triangles with it).

    Raises
    ------
    ValueError
        Not an unstructured grid this reader understands, or its connectivity is not ``nodes`` per cell.
    """
    root = ET.parse(path).getroot()
    if root.get("type") != "UnstructuredGrid":
        raise ValueError(f"{path}: not a VTK unstructured grid")
    header = _NUMPY_TYPES[root.get("header_type", "UInt32")]
    order = "<" if root.get("byte_order", _BYTE_ORDER) == "LittleEndian" else ">"
    conn = [el for el in root.iterfind("UnstructuredGrid/Piece/Cells/DataArray") if el.get("Name") == "connectivity"]
    if not conn:
        raise ValueError(f"{path}: no cells")
    ids = _decode(conn[0], header.newbyteorder(order), root.get("compressor") is not None, order)
    if ids.size % nodes:
        raise ValueError(f"{path}: {ids.size} connectivity entries are not cells of {nodes} points")
    return np.asarray(ids, dtype=np.int64).reshape(-1, nodes)
