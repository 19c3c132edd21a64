"""Minimal reader and writer for Caffe ``.caffemodel`` files (binary protobuf ``NetParameter``).

Only the fields a weight loader needs are decoded (spec §3.1, docs/spec/weights.md); everything else
is skipped by wire type, so no ``caffe`` or ``protobuf`` package is needed.

* ``NetParameter``: ``name = 1``, ``layers = 2`` (legacy V1LayerParameter), ``layer = 100``
  (LayerParameter).
* ``LayerParameter``: ``name = 1``, ``type = 2`` (string), ``blobs = 7``.
* ``V1LayerParameter``: ``name = 4``, ``type = 5`` (``LayerType`` enum), ``blobs = 6``.
* ``BlobProto``: ``shape = 7`` (``BlobShape { dim = 1 }``, int64, packed or not), ``data = 5``
  (float32, packed or not), ``double_data = 8`` (float64), legacy 4-D ``num = 1``,
  ``channels = 2``, ``height = 3``, ``width = 4``.

As in Caffe's ``Blob::FromProto``, a blob with any legacy dimension set has shape
``(num, channels, height, width)``; otherwise it takes ``shape.dim``. Old files therefore give
4-D biases such as ``(1, 1, 1, 96)``: loaders reshape to what they expect.

Not supported (a :class:`ProtoError` or a layer without blobs, never a wrong array): V0 layers
(``V1LayerParameter.layer = 1``, pre-2014 files), protobuf groups (wire types 3 and 4).

:func:`encode_net` writes the same subset, for tests that need synthetic caffemodels.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "CaffeLayer",
    "ProtoError",
    "encode_blob",
    "encode_net",
    "parse_blob",
    "parse_layers",
    "parse_net",
]

# Wire types.
_VARINT, _I64, _LEN, _I32 = 0, 1, 2, 5

# V1LayerParameter.LayerType (caffe.proto), enum value -> V2 type string.
_V1_TYPES: dict[int, str] = {
    0: "None",
    1: "Accuracy",
    2: "BNLL",
    3: "Concat",
    4: "Convolution",
    5: "Data",
    6: "Dropout",
    7: "EuclideanLoss",
    8: "Flatten",
    9: "HDF5Data",
    10: "HDF5Output",
    12: "ImageData",
    14: "InnerProduct",
    15: "LRN",
    17: "Pooling",
    18: "ReLU",
    19: "Sigmoid",
    20: "Softmax",
    21: "SoftmaxWithLoss",
    22: "Split",
    23: "TanH",
    24: "WindowData",
    25: "Eltwise",
    26: "Power",
    29: "MemoryData",
    33: "Slice",
    39: "Deconvolution",
}
_V1_CODES: dict[str, int] = {v: k for k, v in _V1_TYPES.items()}


class ProtoError(ValueError):
    """The bytes are not a (supported) Caffe ``NetParameter``: truncated or corrupt."""


@dataclass
class CaffeLayer:
    """One layer of a caffemodel.

    Attributes:
        name: layer name (``conv1``).
        type: V2 type string (``Convolution``); V1 enums are mapped to the same strings
            (unknown ones read ``V1:<number>``).
        blobs: parameter arrays in file order (weights, then bias), float32 (float64 when the
            file stores ``double_data``), with the stored shape.
    """

    name: str
    type: str
    blobs: list[np.ndarray] = field(default_factory=list)


# ----------------------------------------------------------------------------- decoding


def _varint(buf: memoryview, pos: int) -> tuple[int, int]:
    result = shift = 0
    n = len(buf)
    while True:
        if pos >= n:
            raise ProtoError("truncated varint")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, pos
        shift += 7
        if shift > 63:
            raise ProtoError("varint longer than 10 bytes")


def _fields(buf: memoryview) -> Iterator[tuple[int, int, int | memoryview]]:
    """Yield ``(field number, wire type, value)``; value is an int or a byte view."""
    pos, n = 0, len(buf)
    while pos < n:
        key, pos = _varint(buf, pos)
        num, wire = key >> 3, key & 7
        if num == 0:
            raise ProtoError("field number 0")
        if wire == _VARINT:
            val, pos = _varint(buf, pos)
            yield num, wire, val
        elif wire == _I64:
            if pos + 8 > n:
                raise ProtoError("truncated 64-bit field")
            yield num, wire, buf[pos : pos + 8]
            pos += 8
        elif wire == _LEN:
            length, pos = _varint(buf, pos)
            if pos + length > n:
                raise ProtoError(f"length-delimited field {num} runs past the end of its message")
            yield num, wire, buf[pos : pos + length]
            pos += length
        elif wire == _I32:
            if pos + 4 > n:
                raise ProtoError("truncated 32-bit field")
            yield num, wire, buf[pos : pos + 4]
            pos += 4
        else:
            raise ProtoError(f"unsupported wire type {wire} (field {num})")


def _signed64(v: int) -> int:
    return v - (1 << 64) if v >= 1 << 63 else v


def _packed_varints(buf: memoryview) -> list[int]:
    out, pos = [], 0
    while pos < len(buf):
        v, pos = _varint(buf, pos)
        out.append(_signed64(v))
    return out


def _as_bytes(val: int | memoryview) -> memoryview:
    if not isinstance(val, memoryview):
        raise ProtoError("expected a length-delimited field")
    return val


def _as_int(val: int | memoryview) -> int:
    if not isinstance(val, int):
        raise ProtoError("expected a varint field")
    return val


def _floats(val: int | memoryview, wire: int, dtype: str, chunks: list[np.ndarray]) -> None:
    """Append a packed (wire 2) or unpacked (wire 5 / 1) run of floats to ``chunks``."""
    width = np.dtype(dtype).itemsize
    fixed = _I32 if width == 4 else _I64
    if wire not in (_LEN, fixed):
        raise ProtoError(f"wrong wire type {wire} for a {dtype} array")
    b = _as_bytes(val)
    if len(b) % width:
        raise ProtoError(f"packed {dtype} array of {len(b)} bytes")
    chunks.append(np.frombuffer(b, dtype=dtype))


def parse_blob(buf: bytes | memoryview) -> np.ndarray:
    """Decode one ``BlobProto`` into an array with its stored shape (float32 or float64)."""
    mv = memoryview(buf)
    legacy: dict[int, int] = {}
    dims: list[int] = []
    data: list[np.ndarray] = []
    ddata: list[np.ndarray] = []
    for num, wire, val in _fields(mv):
        if num in (1, 2, 3, 4) and wire == _VARINT:
            legacy[num] = _signed64(_as_int(val))
        elif num == 7 and wire == _LEN:  # BlobShape
            for n2, w2, v2 in _fields(_as_bytes(val)):
                if n2 != 1:
                    continue
                if w2 == _LEN:
                    dims.extend(_packed_varints(_as_bytes(v2)))
                elif w2 == _VARINT:
                    dims.append(_signed64(_as_int(v2)))
                else:
                    raise ProtoError(f"wrong wire type {w2} for BlobShape.dim")
        elif num == 5:
            _floats(val, wire, "<f4", data)
        elif num == 8:
            _floats(val, wire, "<f8", ddata)
    if legacy:
        shape = tuple(legacy.get(k, 0) for k in (1, 2, 3, 4))
    else:
        shape = tuple(dims)
    if data:
        arr = np.concatenate(data) if len(data) > 1 else data[0]
    elif ddata:
        arr = np.concatenate(ddata) if len(ddata) > 1 else ddata[0]
    else:
        arr = np.zeros(0, np.float32)
    if any(d < 0 for d in shape):
        raise ProtoError(f"negative blob dimension {shape}")
    count = int(np.prod(shape, dtype=np.int64)) if shape else arr.size
    if count != arr.size:
        raise ProtoError(f"blob of shape {shape} holds {arr.size} values, expected {count}")
    return arr.reshape(shape) if shape else arr


def _parse_layer(buf: memoryview, legacy: bool) -> CaffeLayer:
    f_name, f_type, f_blobs = (4, 5, 6) if legacy else (1, 2, 7)
    name, ltype, blobs = "", "", []
    for num, wire, val in _fields(buf):
        if num == f_name and wire == _LEN:
            name = bytes(_as_bytes(val)).decode("utf-8", errors="replace")
        elif num == f_type:
            if legacy:
                code = _as_int(val)
                ltype = _V1_TYPES.get(code, f"V1:{code}")
            else:
                ltype = bytes(_as_bytes(val)).decode("utf-8", errors="replace")
        elif num == f_blobs and wire == _LEN:
            blobs.append(parse_blob(_as_bytes(val)))
    return CaffeLayer(name, ltype, blobs)


def parse_layers(data: bytes | memoryview) -> list[CaffeLayer]:
    """Every layer of a serialised ``NetParameter``, V2 (``layer``) and V1 (``layers``) alike.

    Raises:
        ProtoError: truncated or corrupt bytes, or no layer at all.
    """
    layers = []
    for num, wire, val in _fields(memoryview(data)):
        if wire != _LEN:
            continue
        if num == 100:
            layers.append(_parse_layer(_as_bytes(val), legacy=False))
        elif num == 2:
            layers.append(_parse_layer(_as_bytes(val), legacy=True))
    if not layers:
        raise ProtoError("no layers found: not a Caffe NetParameter")
    return layers


def parse_net(data: bytes | memoryview) -> dict[str, list[np.ndarray]]:
    """``{layer name: [blob arrays]}`` of a serialised ``NetParameter``.

    A name that occurs twice (e.g. TRAIN and TEST data layers) keeps the first entry that has
    blobs.
    """
    out: dict[str, list[np.ndarray]] = {}
    for layer in parse_layers(data):
        if layer.name not in out or (not out[layer.name] and layer.blobs):
            out[layer.name] = layer.blobs
    return out


# ----------------------------------------------------------------------------- encoding


def _enc_varint(v: int) -> bytes:
    if v < 0:
        v += 1 << 64
    out = bytearray()
    while True:
        b = v & 0x7F
        v >>= 7
        if v:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _key(num: int, wire: int) -> bytes:
    return _enc_varint((num << 3) | wire)


def _len_field(num: int, payload: bytes) -> bytes:
    return _key(num, _LEN) + _enc_varint(len(payload)) + payload


def encode_blob(
    arr: np.ndarray, legacy_shape: bool = False, packed: bool = True, double: bool = False
) -> bytes:
    """Serialise one array as a ``BlobProto``.

    Args:
        arr: the values; any shape (a legacy shape needs at most 4 dimensions).
        legacy_shape: write ``num/channels/height/width`` (left-padded with 1s to 4-D) instead
            of ``BlobShape``, as pre-2015 files do.
        packed: packed repeated floats (what Caffe writes) or one field per value.
        double: store ``double_data`` instead of ``data``.
    """
    a = np.asarray(arr)
    out = bytearray()
    if legacy_shape:
        if a.ndim > 4:
            raise ValueError("a legacy blob shape has at most 4 dimensions")
        dims = (1,) * (4 - a.ndim) + a.shape
        for num, d in zip((1, 2, 3, 4), dims, strict=True):
            out += _key(num, _VARINT) + _enc_varint(int(d))
    else:
        dims_payload = b"".join(_enc_varint(int(d)) for d in a.shape)
        out += _len_field(7, _len_field(1, dims_payload) if a.ndim else b"")
    num, dtype, wire = (8, "<f8", _I64) if double else (5, "<f4", _I32)
    flat = np.ascontiguousarray(a, dtype=dtype).ravel()
    if packed:
        out += _len_field(num, flat.tobytes())
    else:
        for v in flat:
            out += _key(num, wire) + v.tobytes()
    return bytes(out)


def encode_net(
    name: str,
    layers: Sequence[tuple[str, str, Sequence[np.ndarray]]],
    legacy: bool = False,
    *,
    packed: bool = True,
    double: bool = False,
) -> bytes:
    """Serialise a ``NetParameter`` holding ``layers``: ``[(name, type, [blobs])]``.

    Args:
        name: network name.
        layers: layer name, V2 type string (``Convolution``) and parameter arrays.
        legacy: write V1 ``layers = 2`` entries (type as the ``LayerType`` enum) with legacy
            4-D blob shapes, as old caffemodels do; otherwise V2 ``layer = 100`` with
            ``BlobShape``.
        packed: see :func:`encode_blob`.
        double: see :func:`encode_blob`.
    """
    out = bytearray(_len_field(1, name.encode()))
    for lname, ltype, blobs in layers:
        enc = [encode_blob(b, legacy_shape=legacy, packed=packed, double=double) for b in blobs]
        if legacy:
            if ltype not in _V1_CODES:
                raise ValueError(f"no V1 LayerType enum for {ltype!r}")
            body = _len_field(4, lname.encode()) + _key(5, _VARINT) + _enc_varint(_V1_CODES[ltype])
            body += b"".join(_len_field(6, e) for e in enc)
            out += _len_field(2, body)
        else:
            body = _len_field(1, lname.encode()) + _len_field(2, ltype.encode())
            body += b"".join(_len_field(7, e) for e in enc)
            out += _len_field(100, body)
    return bytes(out)
